//! grpc.health.v1 whose Watch streams end at shutdown (tonic-health's never end, which would hold
//! every shutdown to the full drain timeout).

use std::pin::Pin;

use futures::{Stream, StreamExt};
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_server::Health;
use tonic_health::pb::{HealthCheckRequest, HealthCheckResponse};
use tonic_health::server::{HealthReporter, HealthService};

pub(super) struct ShutdownAwareHealth {
    inner: HealthService,
    shutdown: CancellationToken,
}

impl ShutdownAwareHealth {
    pub(super) fn new(reporter: HealthReporter, shutdown: CancellationToken) -> Self {
        ShutdownAwareHealth {
            inner: HealthService::from_health_reporter(reporter),
            shutdown,
        }
    }
}

#[tonic::async_trait]
impl Health for ShutdownAwareHealth {
    async fn check(
        &self,
        request: Request<HealthCheckRequest>,
    ) -> Result<Response<HealthCheckResponse>, Status> {
        self.inner.check(request).await
    }

    type WatchStream = Pin<Box<dyn Stream<Item = Result<HealthCheckResponse, Status>> + Send>>;

    async fn watch(
        &self,
        request: Request<HealthCheckRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let updates = self.inner.watch(request).await?.into_inner();
        let until = Box::pin(self.shutdown.clone().cancelled_owned());
        let not_serving = ServingStatus::NotServing as i32;
        // Pending updates go out before the end, and the last word is NOT_SERVING.
        let stream = futures::stream::unfold(
            (updates, until, None::<i32>, false),
            move |(mut updates, mut until, last, done)| async move {
                if done {
                    return None;
                }
                tokio::select! {
                    biased;
                    item = updates.next() => {
                        let item = item?;
                        let last = item.as_ref().ok().map(|r| r.status).or(last);
                        Some((item, (updates, until, last, false)))
                    }
                    _ = &mut until => (last != Some(not_serving)).then(|| {
                        let end = HealthCheckResponse { status: not_serving };
                        (Ok(end), (updates, until, last, true))
                    }),
                }
            },
        );
        Ok(Response::new(Box::pin(stream)))
    }
}
