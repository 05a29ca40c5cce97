//! The learner's algorithms behind one trait, so the learner loop, checkpoints and
//! weight publishing do not care which one runs. The files go one way:
//! algorithm.rs (the trait and the [`Entry`] type) and toolbox.rs (what the updates
//! share) name no algorithm; each algorithm names them; registry.rs names each
//! algorithm's entry. This file only declares and re-exports.

mod a2c;
mod algorithm;
mod dense;
pub(crate) mod fused;
mod host_mlp;
pub mod per_dim;
mod ppo;
mod qnet_grad;
mod qrrl;
mod registry;
mod saver;
mod toolbox;
mod vtrace;

pub use crate::config::mlp_dims;
pub use a2c::{A2c, RECOMMENDED_CUSTOM_A2C_LR};
pub use algorithm::{
    AlgoState, Algorithm, Build, Entry, GradPath, UpdateStats, OPTIMIZER_STEPS, RNG_WORD_POS,
};
pub use fused::{threads_for, Loss};
pub use ppo::{
    Ppo, PRESET_PPO_ROLLOUT, RECOMMENDED_PPO_GRAD_CLIP, RECOMMENDED_PPO_LR, RECOMMENDED_PPO_ROLLOUT,
};
pub use qnet_grad::{quantile_net_grads, NetGrads};
pub use qrrl::{qrrl_actor_losses, Qrrl, RECOMMENDED_QRRL_LR};
pub use registry::{build, entry, policy_family, recommended, update_flops, validate};
pub use saver::defaults::{
    CUSTOM_SAVER_GAMMA, CUSTOM_SAVER_LOG_STD_MIN, CUSTOM_SAVER_MINIBATCH_SIZE,
    CUSTOM_SAVER_MU_RAW_PENALTY, CUSTOM_SAVER_PCPN_TUNE_LR, CUSTOM_SAVER_ROLLOUT, HIGH_DIM_ANGLE,
    HIGH_DIM_LOG_STD_MIN, HIGH_DIM_PRETRAIN_BATCHES, RECOMMENDED_SAVER_LR,
};
pub use saver::grad::{
    policy_grads, saver_actor_losses, weighted_quantile_losses, InputGrad, PcpnGrad, SaverLosses,
};
pub use saver::signal as saver_signal;
pub use saver::Saver;
pub(crate) use toolbox::{
    batch_gae, batch_returns, behaviour_log_probs, behaviour_payload_width, bootstrap_and_ends,
    check_finite, gather_rows, gaussian_policy, lambda_targets, matrix, nets_state, no_checks,
    policy_diagnostics, refuse_vtrace, restore_nets, restore_optimizer, run_optimizer,
    saved_number, update_rows,
};
pub use toolbox::{mlp_flops, quantile_net_flops, tau_tensors};
pub(crate) use vtrace::{Vtrace, VTRACE_STATS};

#[cfg(test)]
mod tests;

/// Helpers of the tests that hold a fast path to its autograd reference.
#[cfg(test)]
pub(crate) mod test_util {
    use candle_core::backprop::GradStore;
    use candle_core::Var;

    /// The gradient of `var` in `g`, flattened.
    pub fn grad_of(g: &GradStore, var: &Var) -> Vec<f32> {
        g.get(var.as_tensor())
            .expect("a gradient for every variable")
            .flatten_all()
            .and_then(|t| t.to_vec1())
            .expect("a gradient readable on the host")
    }

    /// (max |want|, max |got − want|): the scale and the worst difference.
    pub fn scale_and_worst(got: &[f32], want: &[f32]) -> (f32, f32) {
        let scale = want.iter().fold(0f32, |m, x| m.max(x.abs()));
        let worst = got
            .iter()
            .zip(want)
            .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        (scale, worst)
    }
}
