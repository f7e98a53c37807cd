//! The evaluators and Replan buffers a replanning thread keeps, one per served policy: request
//! handlers keep one set per thread, batch workers one each. Memory grows with threads and
//! policies, not with sessions.

use std::collections::HashMap;
use std::sync::Arc;

use crate::plan::ReplanScratch;
use crate::policy::{Evaluator, Policy};

/// One policy's networks with their buffers, and Replan's buffers.
pub(crate) struct Workspace {
    pub(crate) evaluator: Evaluator,
    pub(crate) scratch: ReplanScratch,
}

pub(crate) struct Workspaces {
    by_policy: HashMap<*const Policy, Workspace>,
    /// Sizes of a new workspace's buffers: rows per network call, sessions per Replan.
    rows: usize,
    sessions: usize,
}

impl Workspaces {
    pub(super) fn new(rows: usize, sessions: usize) -> Workspaces {
        Workspaces {
            by_policy: HashMap::new(),
            rows,
            sessions,
        }
    }

    /// The workspace for `policy`, made on its first use.
    pub(super) fn get(&mut self, policy: &Arc<Policy>) -> &mut Workspace {
        let key = Arc::as_ptr(policy);
        if !self.by_policy.contains_key(&key) {
            // Policies replaced by a reload, whose sessions are all gone: only we hold them.
            self.by_policy
                .retain(|_, w| Arc::strong_count(w.evaluator.policy()) > 1);
        }
        let (rows, sessions) = (self.rows, self.sessions);
        self.by_policy.entry(key).or_insert_with(|| {
            let (od, ad) = (policy.obs_dim(), policy.act_dim());
            Workspace {
                evaluator: Evaluator::with_capacity(policy.clone(), rows),
                scratch: ReplanScratch::with_capacity(od, ad, sessions),
            }
        })
    }

    /// Forgets every workspace (after a panic left them in an unknown state).
    pub(super) fn clear(&mut self) {
        self.by_policy.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing;

    #[test]
    fn a_policy_replaced_by_a_reload_is_dropped_when_another_arrives() {
        let mut workspaces = Workspaces::new(1, 1);
        let old = Arc::new(testing::toy_policy("toy", 1));
        workspaces.get(&old);
        let weak = Arc::downgrade(&old);
        drop(old);
        assert!(weak.upgrade().is_some(), "the workspace holds the policy");
        let new = Arc::new(testing::toy_policy("toy", 2));
        workspaces.get(&new);
        assert!(weak.upgrade().is_none(), "the replaced policy was freed");
        assert_eq!(workspaces.by_policy.len(), 1);
        workspaces.get(&new);
        assert_eq!(workspaces.by_policy.len(), 1, "a policy has one workspace");
    }
}
