//! The in-process transport: an actor in the same process talks to the hub directly.

use crate::Hub;
use saver_core::link::{Assignment, LearnerLink, LinkError, PolicyWeights, Registration};
use saver_core::rollout::Rollout;
use std::sync::Arc;
use std::time::Duration;

/// A [`LearnerLink`] straight to a [`Hub`].
#[derive(Clone)]
pub struct InProcessLink {
    /// The learner's hub.
    hub: Arc<Hub>,
}

impl InProcessLink {
    /// A link to `hub`.
    pub fn new(hub: Arc<Hub>) -> Self {
        Self { hub }
    }
}

impl LearnerLink for InProcessLink {
    fn register(&mut self, reg: &Registration) -> Result<Assignment, LinkError> {
        self.hub.register(reg)
    }

    fn weights(&mut self, min_version: u64) -> Result<Arc<PolicyWeights>, LinkError> {
        self.hub.wait_weights(min_version)
    }

    fn weights_within(
        &mut self,
        min_version: u64,
        wait: Duration,
    ) -> Result<Arc<PolicyWeights>, LinkError> {
        self.hub.wait_weights_for(min_version, wait)
    }

    fn push(&mut self, rollout: Rollout) -> Result<(), LinkError> {
        self.hub.submit(rollout)
    }
}
