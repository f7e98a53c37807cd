//! A call's deadline, from its `grpc-timeout` header, which gRPC clients send for their own
//! deadline. The server answers DEADLINE_EXCEEDED itself when it passes, and a step answered so
//! is not applied.

use std::time::{Duration, Instant};

use tonic::Status;
use tonic::metadata::MetadataMap;

/// The instant a call's `grpc-timeout` runs out, counted from `received`; None without one.
/// A malformed header is treated as absent, as gRPC servers do.
pub(super) fn of(metadata: &MetadataMap, received: Instant) -> Option<Instant> {
    let text = metadata.get("grpc-timeout")?.to_str().ok()?;
    parse(text).map(|timeout| received + timeout)
}

/// `grpc-timeout` per the gRPC HTTP/2 spec: at most 8 ASCII digits and a unit (H, M, S, m, u, n).
pub(super) fn parse(text: &str) -> Option<Duration> {
    let (digits, unit) = text.split_at(text.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n * 3600),
        "M" => Duration::from_secs(n * 60),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// The answer to a step whose caller's deadline passed before it was applied.
pub(super) fn exceeded() -> Status {
    Status::deadline_exceeded(
        "the call's deadline passed before the step was applied; the session is unchanged",
    )
}

/// Whether `deadline` has passed.
pub(super) fn passed(deadline: Option<Instant>) -> bool {
    deadline.is_some_and(|d| d <= Instant::now())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_every_unit_and_refuses_malformed_values() {
        assert_eq!(parse("3H"), Some(Duration::from_secs(10_800)));
        assert_eq!(parse("2M"), Some(Duration::from_secs(120)));
        assert_eq!(parse("5S"), Some(Duration::from_secs(5)));
        assert_eq!(parse("1m"), Some(Duration::from_millis(1)));
        assert_eq!(parse("250u"), Some(Duration::from_micros(250)));
        assert_eq!(parse("99999999n"), Some(Duration::from_nanos(99_999_999)));
        for bad in ["", "S", "123456789S", "12x", "-1S", "1.5S", " 1S", "1s"] {
            assert_eq!(parse(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn a_deadline_counts_from_the_request() {
        let mut metadata = MetadataMap::new();
        let received = Instant::now();
        assert_eq!(of(&metadata, received), None);
        metadata.insert("grpc-timeout", "20m".parse().unwrap());
        assert_eq!(
            of(&metadata, received),
            Some(received + Duration::from_millis(20))
        );
    }
}
