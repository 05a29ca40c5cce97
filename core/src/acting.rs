//! An algorithm's behaviour policy, seen from both ends of a rollout: actors act with
//! it ([`ActingPolicy`]) and record, per step, the payload its family declares (the
//! Gaussian's mean and log-std today, a quantile sample tomorrow); the learner holds
//! what arrives to that declaration ([`PolicyFamily::check`]). Which family an
//! algorithm uses is its own choice ([`crate::algo::entry`]).

use crate::env::EnvLayout;
use crate::rng::SaverRng;
use crate::Result;
use saver_proto::NamedTensor;
use std::collections::BTreeMap;
use std::sync::Arc;

/// A policy over one version of the published weights, as an actor runs it.
pub trait ActingPolicy: Send {
    /// The version of the weights in use.
    fn version(&self) -> u64;
    /// Samples an action for `obs` into `action` ([`EnvLayout::action_dim`] values)
    /// and writes the step's payload ([`PolicyFamily::payload_width`] values).
    fn act(
        &mut self,
        obs: &[f32],
        rng: &mut SaverRng,
        action: &mut Vec<f32>,
        payload: &mut Vec<f32>,
    );
    /// The policy's most likely action for `obs` (evaluation without exploration).
    fn act_deterministic(&mut self, obs: &[f32], action: &mut Vec<f32>);
}

/// A kind of behaviour policy: what it records per step, what values those may take,
/// and how to act with published weights.
pub trait PolicyFamily: Send + Sync + std::fmt::Debug {
    /// Its name on the wire (RegisterReply.settings.policy.family).
    fn name(&self) -> &'static str;
    /// Payload values per step.
    fn payload_width(&self) -> usize;
    /// What the payload holds, in order, for people and foreign clients.
    fn payload_layout(&self) -> String;
    /// The numbers a foreign actor needs to act as this family does (e.g. the
    /// Gaussian's bounds; inf where there is none).
    fn params(&self) -> BTreeMap<String, f64>;
    /// Checks the payload and actions of `steps` steps (shapes already checked):
    /// every value in range and every action one this policy could have drawn; the
    /// error names the first value that is not.
    fn check(&self, payload: &[f32], actions: &[f32], steps: usize) -> Result<()>;
    /// A policy acting with `weights`; refused when they do not fit.
    fn acting(&self, weights: Arc<PolicyWeights>) -> Result<Box<dyn ActingPolicy>>;
    /// The env layout it acts in.
    fn layout(&self) -> EnvLayout;
    /// How to compute an action from the published weights, in words a client in any
    /// language can follow (tensor names, shapes, activations, the sampling).
    fn architecture(&self) -> String;
}

/// One published version of the agent's weights, shared (never copied) by all readers.
#[derive(Debug)]
pub struct PolicyWeights {
    /// Number of updates behind these weights.
    pub version: u64,
    /// The agent's tensors (`agent.*`).
    pub tensors: Vec<NamedTensor>,
}

impl PolicyWeights {
    /// The tensor named `name`.
    pub fn get(&self, name: &str) -> Option<&NamedTensor> {
        self.tensors.iter().find(|t| t.name == name)
    }
}
