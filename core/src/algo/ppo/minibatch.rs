//! What one PPO minibatch step reads (its rows, gathered from the batch) and what it
//! adds up for the update's stats: shared by the candle reference and the fast path.

/// One minibatch's rows, gathered from the batch (row-major on the host).
pub(super) struct Minibatch {
    /// Steps.
    pub(super) n: usize,
    /// [n, obs_dim].
    pub(super) obs: Vec<f32>,
    /// [n, action_dim].
    pub(super) actions: Vec<f32>,
    /// [n].
    pub(super) old_logp: Vec<f32>,
    /// [n], normalised with `ppo.adv_norm`.
    pub(super) advantage: Vec<f32>,
    /// [n, c].
    pub(super) returns: Vec<f32>,
    /// [n, c].
    pub(super) old_value: Vec<f32>,
}

/// Sums over the minibatch steps of one update, for its stats.
#[derive(Default)]
pub(super) struct Totals {
    pub(super) policy_loss: f64,
    pub(super) value_loss: f64,
    pub(super) entropy: f64,
    pub(super) approx_kl: f64,
    pub(super) clip_fraction: f64,
    pub(super) grad_norm: f64,
    pub(super) steps: usize,
}
