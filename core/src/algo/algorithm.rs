//! The contract every algorithm meets ([`Algorithm`]), what it checkpoints
//! ([`AlgoState`]), and what it registers ([`Entry`]): the types the algorithms and the
//! registry both name, so that neither reaches the other through them.

use crate::acting::PolicyFamily;
use crate::config::RunConfig;
use crate::nets::Pcpn;
use crate::optim::Optimizer;
use crate::rollout::Batch;
use crate::Result;
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Losses and diagnostics of one update, by name (the names of
/// [`Algorithm::stat_names`]).
#[derive(Clone, Debug, PartialEq)]
pub struct UpdateStats {
    /// (name, value) pairs.
    pub values: Vec<(&'static str, f32)>,
    /// Per-dimension diagnostics (name, one value per coordinate or action entry;
    /// [`crate::algo::per_dim`]), for the run's per_dim.csv; empty where an algorithm has none.
    pub per_dim: Vec<(&'static str, Vec<f32>)>,
}

impl UpdateStats {
    /// The value named `name`.
    pub fn get(&self, name: &str) -> Option<f32> {
        self.values
            .iter()
            .find(|(n, _)| *n == name)
            .map(|&(_, v)| v)
    }
}

/// A learning algorithm: updates from batches and exposes its state.
pub trait Algorithm: Send {
    /// Names of the values in [`UpdateStats`] (CSV columns).
    fn stat_names(&self) -> Vec<&'static str>;
    /// One update from a batch. [`crate::CoreError::NonFinite`] when the batch makes a loss
    /// or gradient non-finite: then nothing changed (weights, optimiser slots and step
    /// count are as before) and the caller may go on with the next batch.
    fn update(&mut self, batch: &Batch) -> Result<UpdateStats>;
    /// The agent's weights (`agent.*`), what actors need.
    fn policy_tensors(&self) -> Result<Vec<NamedTensor>>;
    /// Optimiser steps taken.
    fn optimizer_steps(&self) -> u64;
    /// Threads the update may use beyond candle's own (0: one per core); an
    /// execution option that never changes the results. Ignored by single-threaded
    /// updates.
    fn set_threads(&mut self, _n: usize) {}
    /// Which gradient implementation the update runs (the hand-written host path by
    /// default on the CPU); for the tests and `saver bench` that hold the fast paths to
    /// candle autograd. Ignored by algorithms with one path.
    fn set_grad_path(&mut self, _path: GradPath) {}
    /// Everything a checkpoint needs to go on exactly: every trainable tensor, the
    /// optimiser slots, and numbers such as the step count and random-stream position.
    fn save_state(&self) -> Result<AlgoState>;
    /// Restores what [`Algorithm::save_state`] saved (`get` finds its tensors by name).
    fn restore_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        numbers: &BTreeMap<String, u128>,
    ) -> Result<()>;
}

/// An algorithm's checkpointed state.
#[derive(Debug, Default)]
pub struct AlgoState {
    /// Named tensors (weights, optimiser slots).
    pub tensors: Vec<(String, Tensor)>,
    /// Named counters (stored in the checkpoint's metadata).
    pub numbers: BTreeMap<String, u128>,
}

impl AlgoState {
    /// The saved tensor `name` (what [`Algorithm::restore_state`]'s `get` looks up).
    pub fn get(&self, name: &str) -> Option<Tensor> {
        self.tensors
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, t)| t.clone())
    }
}

/// Key of the optimiser's step count in [`AlgoState::numbers`].
pub const OPTIMIZER_STEPS: &str = "optimizer_steps";
/// Key of the learner's random-stream position (SAVER's τ draws).
pub const RNG_WORD_POS: &str = "rng_word_pos";

impl AlgoState {
    /// The networks' `tensors` with `opt`'s slots and step count.
    pub(crate) fn with_optimizer(mut tensors: Vec<(String, Tensor)>, opt: &Optimizer) -> Self {
        tensors.extend(opt.slots());
        let numbers = [(OPTIMIZER_STEPS.to_string(), opt.steps() as u128)];
        Self {
            tensors,
            numbers: numbers.into_iter().collect(),
        }
    }
}

/// How the agent's gradient through the PCPN is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradPath {
    /// Hand-written forward and input-gradient of the frozen PCPN (the default on the CPU).
    Fast,
    /// candle autograd through the whole graph (the reference the fast path is tested
    /// against; the default on other devices).
    Reference,
}

impl GradPath {
    /// The fused blocks run on the host; on a GPU candle's graph keeps everything on
    /// the device.
    pub fn for_device(dev: &Device) -> Self {
        if dev.is_cpu() {
            Self::Fast
        } else {
            Self::Reference
        }
    }
}

/// Builds an algorithm's learner side from the run's config (and the frozen PCPN, for
/// algorithms that use one).
pub type Build = fn(&RunConfig, Option<Pcpn>, &Device) -> Result<Box<dyn Algorithm>>;

/// What an algorithm brings: its learner, its actors' behaviour policy, its defaults,
/// its own checks of a config and the work of its update.
#[derive(Clone, Copy)]
pub struct Entry {
    /// The learner side, from the run's config (and the frozen PCPN, for algorithms
    /// that use one).
    pub build: Build,
    /// The behaviour policy actors run, and what its rollouts record per step.
    pub policy: fn(&RunConfig) -> Arc<dyn PolicyFamily>,
    /// Its defaults: what it changes in the paper's settings for `config.env`
    /// ([`crate::algo::recommended`]; `--faithful` skips it).
    pub recommend: fn(&mut RunConfig),
    /// Its refusals of a config, beyond the checks every run gets ([`crate::algo::validate`]).
    pub check: fn(&RunConfig) -> Result<()>,
    /// FLOPs of one update on `b` steps of `t` trajectories (multiply-add = 2; a
    /// trained dense layer 3× its forward, a frozen one 2×), for `saver bench`.
    pub flops: fn(&RunConfig, usize, usize) -> f64,
}
