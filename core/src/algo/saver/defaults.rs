//! SAVER's defaults ([`crate::algo::Entry::recommend`]) and the work of its update
//! ([`crate::algo::Entry::flops`]).
//!
//! SAVER with the smallest set of changes that make it learn (results/README.md has
//! the ablations): TF1 Adam at 1e-3 instead of RMSProp at the paper's rate, μ = tanh(raw)
//! and log σ in [-4.6, 0] so the actions stay where the PCPN was pretrained, the vector
//! advantage centred per dimension over each batch and divided by one standard deviation
//! over all dimensions, and a PCPN pretrained 5,000 batches (its held-out loss settles
//! by ~1,000). From d = 8 on the angle env, the paper's 100,000-batch PCPN and a floor
//! on σ; on a custom env, the saturation wall, a PCPN that keeps learning on the
//! policy's steps, a floor on σ and four optimiser steps per batch.

use crate::algo::{mlp_dims, mlp_flops};
use crate::config::{HeadConfig, ObsNorm, OptimizerKind, RunConfig};
use crate::env::EnvKind;

/// SAVER's learning rate by default (with Adam; the paper's is 0.01 with RMSProp).
/// 3e-4 before: at d = 16 it left SAVER at a mean length of 1000 for 2.56 M steps,
/// where 1e-3 moves every coordinate toward the goal ~2x as fast (results/README.md).
pub const RECOMMENDED_SAVER_LR: f64 = 1e-3;
/// From this dimension on, SAVER's default on the angle env is
/// [`HIGH_DIM_PRETRAIN_BATCHES`] and [`HIGH_DIM_LOG_STD_MIN`] (issue 19,
/// results/README.md): with the 5,000-batch PCPN and σ free to fall, the angle entry
/// of a pair sinks to its pole (the pair then moves along one axis) and d = 8 and 16
/// lose what they learned.
pub const HIGH_DIM_ANGLE: usize = 8;
/// Pretraining batches of SAVER's default on angle from [`HIGH_DIM_ANGLE`] on: the
/// paper's 100,000 (its PCPN's gradient is the only signal; 3,000 → 100,000 batches
/// take its in-pair cosine at d = 16 from 0.67 to 0.83, `saver diagnose pcpn`).
pub const HIGH_DIM_PRETRAIN_BATCHES: u64 = 100_000;
/// The floor on log σ of SAVER's default on angle from [`HIGH_DIM_ANGLE`] on (σ ≥ 0.2:
/// a pair at its pole gets out in proportion to σ, `bench/angle_pole.py`).
pub const HIGH_DIM_LOG_STD_MIN: f64 = -1.6;
/// SAVER's saturation penalty ([`SaverConfig::mu_raw_penalty`]) on a custom env: in the
/// inertial envs measured (issue 31) μ ran into the tanh bound and stayed there (the
/// point mass: 16 % / 42 % of rows at the bound by 300 k steps, 100 % on a seed that
/// collapsed); with the wall the point mass reaches 0.93 mean success over five seeds
/// (0.79 without, A2C 0.84) and Reacher ends nearer the target than A2C on 4 of 5
/// (results/README.md, "Inertial envs").
pub const CUSTOM_SAVER_MU_RAW_PENALTY: f64 = 0.1;
/// The PCPN's own training on the policy's steps ([`SaverConfig::pcpn_tune_lr`]) on a
/// custom env: a PCPN pretrained on random walks errs most where a trained policy goes
/// (the point mass: its error on the steps taken grew from 4.7 to 15.7 times the
/// action's effect over 300 k steps; tuned at 1e-3 it fell to 0.3), and the learner
/// cannot send the walks of an env it cannot reset at will there. On the point mass
/// (one PCPN, five seeds) success rose from 0.82 frozen to 0.95 at 1e-4 (0.96 at 1e-3);
/// on Reacher-v5 (one PCPN, seeds 0-2) from 0.53 frozen to 0.94 at 1e-4, while 1e-3,
/// whose steps jitter the PCPN's output by more than an action effect of ~1 % of Δp's
/// spread, reached 0.53 (results/README.md, "A PCPN that follows the policy").
pub const CUSTOM_SAVER_PCPN_TUNE_LR: f64 = 1e-4;
/// Rows of each batch the PCPN's own training step reads on a custom env
/// ([`SaverConfig::pcpn_tune_rows`], drawn at random): a pretraining batch's 128. On all
/// 512 rows of a batch that step was a quarter of SAVER's update on Reacher-v5. Three
/// seeds at 200 k steps end where all rows left them: success 0.98 / 0.98 / 0.96
/// against 1.00 / 0.96 / 1.00, return −4.07 … −4.43 against −3.96 … −4.26
/// (results/env-return/README.md, "2026-12-08, later: a lighter PCPN and the host step").
pub const CUSTOM_SAVER_PCPN_TUNE_ROWS: usize = 128;
/// τ samples per row of SAVER's actor loss on a custom env ([`SaverConfig::quantiles`];
/// the paper's 32 on the presets). The fused blocks of the input gradient and of the
/// PCPN's training step scale with K. With [`CUSTOM_SAVER_PCPN_TUNE_ROWS`] the update on
/// Reacher-v5's shape takes 51 ms instead of 75 through candle (28-30 ms instead of 53-55
/// on the host step, `saver bench`'s custom-env row), and three seeds at 200 k reach
/// 0.96 / 1.00 / 0.98 success at a return of −4.17 … −4.27 (K = 32 and every row: 1.00 /
/// 0.96 / 1.00, −3.96 … −4.26); at K = 8 one seed of three fell to 0.92, −4.65.
pub const CUSTOM_SAVER_QUANTILES: usize = 16;
/// PCPN pretraining batches of SAVER on a custom env (`pretrain.batches`; 5,000 on the
/// presets), at [`CUSTOM_PRETRAIN_QUANTILES`] τ per sample: the wait before a custom
/// env's first step, most of it these batches, fell from 24 s to 10-12 s on Reacher-v5
/// (65,536 walk samples from 8 envs, 2 cores), while the PCPN goes on learning on the
/// policy's own steps ([`CUSTOM_SAVER_PCPN_TUNE_LR`]). With both, five seeds per env:
/// Reacher-v5 at 1 M 1.00 on every seed, return −3.67 … −3.86 (mean −3.79; the 5,000 ×
/// 32 PCPN −3.77 … −3.95, −3.86); the point mass at 15 k 0.92-0.98 (every seed past
/// 0.9; that PCPN 0.88-0.98) (results/env-return/README.md, "2026-12-08, later: a lighter PCPN and the host step").
pub const CUSTOM_PRETRAIN_BATCHES: u64 = 2_500;
/// τ samples per pretraining sample of SAVER on a custom env (`pretrain.quantiles`; the
/// paper's 32 on the presets): half the fused blocks' work per batch
/// ([`CUSTOM_PRETRAIN_BATCHES`]).
pub const CUSTOM_PRETRAIN_QUANTILES: usize = 16;
/// SAVER's discount on a custom env: a horizon of ~30 steps instead of ~100, with the
/// progress completed at success ([`RunConfig::complete_at_success`]). The progress
/// reward |p − g| − |p' − g| telescopes, so what a step's action changes in the return
/// is the next few steps' distance, while a 100-step horizon adds 100 steps of action
/// noise to every row's return: where the point mass stopped short of its goal, the
/// one-rollout advantage of pushing towards it had a signal-to-noise ratio of 0.15 at
/// γ = 0.99 and 1.06 at 0.9 (`bench/hover_advantage.py`). But the horizon also sets
/// what speed is worth: at 0.9 Reacher-v5's policy opens with a hard push and pays
/// most of its return in the env's control cost. At 0.97 with the completed progress
/// (stopping short of the box then costs the whole remainder) Reacher's return is at
/// least SB3 PPO's and our A2C's on 14 of 15 seeds over three pretrainings (γ = 0.9
/// without it: 7 of 10), for a little of the point mass's precision (over five
/// pretrainings 14 of 25 seeds at 1.00 success against 17, mean 0.96 against 0.97;
/// docs/ALGORITHM.md §7.1, results/README.md, "The custom-env default since
/// 2026-12-04").
pub const CUSTOM_SAVER_GAMMA: f64 = 0.97;
/// SAVER's rollout length on a custom env: at γ = 0.9 a 64-step rollout makes each
/// row's return nearly the Monte-Carlo one that `bench/hover_advantage.py` measures
/// (the critic's bootstrap weighs 0.9^64 ≈ 0.001 after 64 steps, 0.43 after 8). With
/// both, five seeds on one PCPN per env: the point mass reaches its goal in 0.97 of the
/// episodes and Reacher-v5 in 0.91. At γ = 0.99 with 8 steps (the default before) they
/// reach 0.90 and 0.95 (seeds 0-2), at γ = 0.9 with 8 steps 1.00 and 0.76: this is the
/// best worst case of the three (results/README.md, "The discount on custom envs").
/// The learner also makes an eighth of the updates (a 512-step batch from 8 envs).
/// (Measured at γ = 0.9; at today's 0.97 the bootstrap weighs 0.97^64 ≈ 0.14.)
pub const CUSTOM_SAVER_ROLLOUT: u32 = 64;
/// SAVER's learning rate on a custom env falls linearly to zero over the run
/// (`lr_decay`). Where the point mass misses, its deterministic policy stops at rest
/// beside the box: the set point of its mean action (`bench/setpoint_offset.py`) lies
/// outside the box for up to 24 % of the goals on a seed at 0.82 success. The decay
/// leaves the median set point where it was but trims those tails: over five seeds on
/// each of two PCPNs, mean success 0.99 and 0.98 against 0.93 and 0.95, return −15.7
/// and −15.4 against −17.1 and −16.5; on Reacher-v5 (one PCPN) return at least SB3
/// PPO's and our A2C's on 5 of 5 seeds, mean −7.6 against −11.7 (4 of 5), success 0.89
/// against 0.85 (results/README.md, "Where the mean action holds the mass").
pub const CUSTOM_SAVER_LR_DECAY: bool = true;

/// Where SAVER's log σ starts on a custom env (σ = 0.45, where the agent's default
/// start is 0.37), with the floor [`CUSTOM_SAVER_LOG_STD_MIN`] below it. Where one
/// step's position change is mostly velocity (the point masses: the action causes
/// 1.5-2 % of Δp's spread) SAVER's only gradient on σ, through the PCPN's dependence on
/// it, is weak and σ stays near its start for the whole run; the action's share of Δp
/// grows with σ² and the PCPN's error against the action's effect falls, so a start
/// (a floor until 2026-12-07) of 0.45 lets the ranks that steer the mean carry more of
/// the action, and several optimiser steps per batch ([`CUSTOM_SAVER_MINIBATCH_SIZE`])
/// no longer drive σ down (results/README.md, "Exploration noise and optimiser steps").
pub const CUSTOM_SAVER_LOG_STD_INIT: f64 = -0.8;
/// The floor on log σ of SAVER on a custom env (σ ≥ 0.2), below its start
/// [`CUSTOM_SAVER_LOG_STD_INIT`]: where the env's own reward charges for noise and
/// imprecision (Reacher-v5's control cost and distance), the env-return term's score
/// function lowers σ, and a floor at the start (0.45, the default until 2026-12-07)
/// held it there. On Reacher-v5 at 1 M steps the floor at 0.2 took the whole-episode
/// return from −4.3 … −4.8 to −3.7 … −3.8 (the tuned PPO's −3.7); on the point mass,
/// whose σ stays near its start, success stays 1.00 on 5 of 5 seeds
/// (results/env-return/README.md, "2026-12-07, later").
pub const CUSTOM_SAVER_LOG_STD_MIN: f64 = -1.6;
/// SAVER's minibatch on a custom env: each pass over a batch in minibatches of this
/// many steps (4 optimiser steps per pass over a 512-step batch of 8 envs; two passes,
/// [`CUSTOM_SAVER_EPOCHS`]). With one step per batch
/// SAVER's mean action stays soft (at rest 0.6 from the goal it pushes 0.75-0.78 where
/// SB3 PPO pushes 1.0, and its gain near the goal is a third of PPO's: slower
/// approaches, and set points outside the box); four steps per batch with σ held at the
/// floor reach the goal in every evaluation episode of 5 of 5 seeds on the point mass
/// in three coordinates (results/README.md, "Exploration noise and optimiser steps").
/// The push that is left (0.82) is the bound of the mean under that noise: `--mu-bound
/// 1.5` pushes 1.0 and matches SB3 PPO's return where the return is the distance, but
/// costs Reacher-v5's control, so the bound stays 1.
pub const CUSTOM_SAVER_MINIBATCH_SIZE: usize = 128;
/// Passes over each batch of SAVER on a custom env (in minibatches of
/// [`CUSTOM_SAVER_MINIBATCH_SIZE`]: 8 optimiser steps per 512-step batch), with the
/// env-return term clipped at [`CUSTOM_SAVER_ENV_CLIP`] so that its rows stop pushing
/// once the policy has moved past the one that acted. At short budgets the update is
/// what limits SAVER (the point mass at 20 k steps: 40 batches): five seeds on one PCPN
/// per env, the point mass at 20 k from 0.82 mean success (worst 0.68) to 0.95 (0.94),
/// Reacher-v5 at 200 k from 0.56 (0.48), return −4.58, to 0.70 (0.64), −4.05; at the
/// long budgets nothing is lost (the point mass at 300 k: 1.00 on 5 of 5, return −13.3
/// against −14.0; Reacher-v5 at 1 M: 0.98-1.00, −3.60 against one pass's −3.66). Four
/// passes were worse on the point mass (0.88, worst 0.62) and, without the clip, on
/// Reacher (results/env-return/README.md, "2026-12-07, night: two passes").
pub const CUSTOM_SAVER_EPOCHS: usize = 2;
/// ε of SAVER's clipped env-return term on a custom env ([`CUSTOM_SAVER_EPOCHS`]).
pub const CUSTOM_SAVER_ENV_CLIP: f64 = 0.2;
/// The weight of SAVER's env-return term on a custom env (docs/ALGORITHM.md §7.2): its
/// push on μ and log σ three times the PCPN term's. The progress reward does not see
/// what else the env's reward counts (Reacher-v5's control cost). On Reacher-v5 (1 M
/// steps, episodes going on past success, [`CUSTOM_SAVER_CONTINUE_PAST_SUCCESS`]) the
/// whole episode's return was −5.4 … −6.2 at w = 1 (3 seeds), −4.6 … −5.1 at w = 2 and
/// −4.3 … −4.8 at w = 3, success 0.94-0.98; the control cost of the approach falls
/// as w grows (seed 1: Σa² 4.05 at w = 1, 2.05 at w = 2) while the approach takes a
/// few steps longer (results/env-return/). Ending episodes at success instead left what
/// the policy does at the goal untrained: −11.0 … −12.2 at w = 1 over 5 seeds. A fixed
/// weight (0.3, before the ratio) handed the update to the env term and broke the point
/// mass (success 4 % at 150 k). Presets send no env reward: the paper's update.
pub const CUSTOM_SAVER_ENV_REWARD: f64 = 3.0;
/// Whether a custom env's episodes go on past success by default for SAVER
/// ([`RunConfig::continue_past_success`]): what the policy does at the goal then costs
/// what the env charges for it (Reacher-v5: −4.3 … −4.8 over the whole episode against
/// −11.0 … −12.2 when episodes ended at success), and a step that starts inside the box
/// learns only from the env's reward. An env without a success radius has no success
/// to go past; one whose reward is the progress keeps its progress at the goal.
pub const CUSTOM_SAVER_CONTINUE_PAST_SUCCESS: bool = true;

/// How SAVER's agent and critics read a custom env's observations: p and g by their
/// running statistics where p spreads under a third of the widest other entry over the
/// first batch, raw otherwise. Both of `running`'s effects sit in the agent's input:
/// Reacher-v5's fingertip offset (0.2 of its joint cosines' spread) read at unit
/// spread took its success at 200 k steps from 0.76 (0.66-0.90) to 0.94 (0.92-0.98),
/// while every entry scaled up cost the point mass, whose p is its widest entry
/// (0.97 → 0.80 with p and g scaled, 0.52 with all); `auto` leaves it, the point mass
/// in three coordinates and reach3 raw (results/env-return/README.md, "where the
/// observation scale acts").
pub const CUSTOM_SAVER_OBS_NORM: ObsNorm = ObsNorm::Auto;

/// GAE's λ of SAVER's vector term on a custom env (`saver.gae_lambda`; the env term
/// keeps `saver.env_gae_lambda` 1, as λ on it cost Reacher-v5's success and return).
/// The progress reward telescopes, so the last rows' bootstrapped values carry most of
/// a short run's signal: at 15 k steps the point mass reached 0.9 success on every seed
/// (0.90-1.00) at λ 0.8 against 0.66-0.82 at 1 (0.9: 0.84-1.00; 0.95: 0.82-0.96), and
/// with the p-scaling of [`CUSTOM_SAVER_OBS_NORM`] Reacher-v5 at 200 k 0.96-1.00 (λ 1:
/// 0.92-0.98), at 1 M 0.96-1.00 at a return of −3.86 (λ 1: −3.64), reach3 −2.1 against
/// −2.9, both point masses 1.00 at 300 k (results/env-return/README.md, "where the
/// observation scale acts").
pub const CUSTOM_SAVER_GAE_LAMBDA: f64 = 0.8;

/// SAVER's defaults over the paper's settings.
pub(crate) fn recommend(c: &mut RunConfig) {
    c.optimizer = OptimizerKind::Adam;
    c.lr = RECOMMENDED_SAVER_LR;
    c.head = HeadConfig::IN_PCPN_DOMAIN;
    c.saver.adv_norm = true;
    c.saver.adv_norm_joint = true;
    if c.env.kind() == Some(EnvKind::Angle) && c.env.dim() >= HIGH_DIM_ANGLE {
        c.pretrain.batches = HIGH_DIM_PRETRAIN_BATCHES;
        c.head.log_std_bounds = c
            .head
            .log_std_bounds
            .map(|(_, max)| (HIGH_DIM_LOG_STD_MIN, max));
    }
    if c.env.kind().is_none() {
        c.saver.mu_raw_penalty = CUSTOM_SAVER_MU_RAW_PENALTY;
        c.saver.pcpn_tune_lr = CUSTOM_SAVER_PCPN_TUNE_LR;
        c.saver.pcpn_tune_rows = CUSTOM_SAVER_PCPN_TUNE_ROWS;
        c.saver.quantiles = CUSTOM_SAVER_QUANTILES;
        c.pretrain.batches = CUSTOM_PRETRAIN_BATCHES;
        c.pretrain.quantiles = CUSTOM_PRETRAIN_QUANTILES;
        c.gamma = CUSTOM_SAVER_GAMMA;
        c.rollout = CUSTOM_SAVER_ROLLOUT;
        c.complete_at_success = true;
        c.lr_decay = CUSTOM_SAVER_LR_DECAY;
        c.saver.minibatch_size = CUSTOM_SAVER_MINIBATCH_SIZE;
        c.saver.epochs = CUSTOM_SAVER_EPOCHS;
        c.saver.env_clip = CUSTOM_SAVER_ENV_CLIP;
        c.saver.obs_norm = CUSTOM_SAVER_OBS_NORM;
        c.saver.gae_lambda = CUSTOM_SAVER_GAE_LAMBDA;
        c.saver.env_reward = CUSTOM_SAVER_ENV_REWARD;
        c.continue_past_success = CUSTOM_SAVER_CONTINUE_PAST_SUCCESS;
        c.head.log_std_bounds = c
            .head
            .log_std_bounds
            .map(|(_, max)| (CUSTOM_SAVER_LOG_STD_MIN, max));
        c.head.log_std_init = CUSTOM_SAVER_LOG_STD_INIT;
    }
}

/// The agent and the vector critic are trained; the frozen PCPN's trunk runs once per
/// step and its heads over the B·K·d quantile rows, forward and input gradient. With
/// several passes (`saver.epochs`, `saver.minibatch_size`) agent and critic run forward
/// once over every row at the update's start, then each pass trains all three over the
/// B steps again.
pub(crate) fn flops(config: &RunConfig, b: usize, t: usize) -> f64 {
    let (l, k) = (&config.env.layout(), config.saver.quantiles);
    let h = &config.hidden;
    let agent = |rows| mlp_flops(rows, &mlp_dims(l.obs_dim, h, l.mu_dim()));
    let critic = |rows| mlp_flops(rows, &mlp_dims(l.pcpn_input_dim(), h, l.aligned_dim));
    let (pcpn, embed) = crate::algo::quantile_net_flops(b, k, l.pcpn_input_dim(), l.aligned_dim);
    let pass = |rows| 3.0 * (agent(rows) + critic(rows));
    if config.saver.one_step(b) {
        return pass(b + t) + 2.0 * (pcpn + embed);
    }
    let epochs = config.saver.epochs as f64;
    agent(b + t) + critic(b + t) + epochs * (pass(b) + 2.0 * (pcpn + embed))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::{recommended, validate};
    use crate::config::{Algo, RunConfig, RECOMMENDED_PRETRAIN_BATCHES};
    use crate::env::EnvSpec;

    /// SAVER's default on angle takes the paper's pretraining and a σ floor from
    /// d = 8 on, and nowhere else (d = 4, select, arm and A2C keep theirs).
    #[test]
    fn saver_on_high_dim_angle_defaults_to_the_long_pcpn_and_a_sigma_floor() {
        let cfg = |kind, d, algo| recommended(&EnvSpec::new(kind, d).unwrap(), algo, 1);
        for d in [8, 16] {
            let c = cfg(EnvKind::Angle, d, Algo::Saver);
            assert_eq!(c.pretrain.batches, 100_000);
            assert_eq!(c.head.log_std_bounds, Some((-1.6, 0.0)));
            validate(&c).unwrap();
        }
        let low = cfg(EnvKind::Angle, 4, Algo::Saver);
        assert_eq!(low.pretrain.batches, RECOMMENDED_PRETRAIN_BATCHES);
        assert_eq!(low.head.log_std_bounds, Some((-4.6, 0.0)));
        for c in [
            cfg(EnvKind::Angle, 16, Algo::A2c),
            cfg(EnvKind::Select, 6, Algo::Saver),
        ] {
            assert_ne!(
                c.head.log_std_bounds.map(|b| b.0),
                Some(-1.6),
                "{:?}",
                c.env
            );
        }
    }

    /// The saturation wall, the tuned PCPN, γ = 0.97, 64-step rollouts, the progress
    /// completed at success, the decaying rate, the σ floor, and minibatches over two
    /// passes with the clipped env term are SAVER's defaults on custom envs only: every
    /// preset (and so results/fig3-5) keeps the paper's 0, 0.99, 8, plain progress,
    /// constant rate and one step per batch, as does `--faithful`, and A2C never has
    /// them; a preset refuses the completion.
    #[test]
    fn saver_on_a_custom_env_takes_its_own_defaults_and_no_preset_or_a2c_does() {
        let custom = EnvSpec::unit_custom("pointmass", 0.2).unwrap();
        let c = recommended(&custom, Algo::Saver, 1);
        assert_eq!(c.saver.mu_raw_penalty, CUSTOM_SAVER_MU_RAW_PENALTY);
        assert_eq!(c.saver.pcpn_tune_lr, CUSTOM_SAVER_PCPN_TUNE_LR);
        assert_eq!(
            (c.saver.pcpn_tune_rows, c.saver.quantiles),
            (CUSTOM_SAVER_PCPN_TUNE_ROWS, CUSTOM_SAVER_QUANTILES)
        );
        let faithful = RunConfig::paper(&custom, Algo::Saver, 1);
        assert_eq!(
            (faithful.saver.pcpn_tune_rows, faithful.saver.quantiles),
            (0, 32)
        );
        assert_eq!(
            (c.gamma, c.rollout),
            (CUSTOM_SAVER_GAMMA, CUSTOM_SAVER_ROLLOUT)
        );
        assert!(c.complete_at_success);
        assert!(c.lr_decay);
        assert_eq!(c.saver.minibatch_size, CUSTOM_SAVER_MINIBATCH_SIZE);
        assert_eq!(
            (c.saver.epochs, c.saver.env_clip),
            (CUSTOM_SAVER_EPOCHS, CUSTOM_SAVER_ENV_CLIP)
        );
        assert_eq!(c.head.log_std_bounds, Some((CUSTOM_SAVER_LOG_STD_MIN, 0.0)));
        assert_eq!(c.head.log_std_init, CUSTOM_SAVER_LOG_STD_INIT);
        assert_eq!(c.saver.env_reward, CUSTOM_SAVER_ENV_REWARD);
        assert_eq!(c.continue_past_success, CUSTOM_SAVER_CONTINUE_PAST_SUCCESS);
        assert_eq!(
            RunConfig::paper(&custom, Algo::Saver, 1).saver.env_reward,
            0.0
        );
        assert_eq!(recommended(&custom, Algo::A2c, 1).saver.env_reward, 0.0);
        let paper = RunConfig::paper(&custom, Algo::Saver, 1);
        assert_eq!(
            (paper.saver.minibatch_size, paper.head.log_std_bounds),
            (0, None)
        );
        assert_eq!((paper.saver.epochs, paper.saver.env_clip), (1, 0.0));
        assert_eq!(c.saver.obs_norm, CUSTOM_SAVER_OBS_NORM);
        assert_eq!(paper.saver.obs_norm, ObsNorm::Off);
        assert_eq!(
            (c.saver.gae_lambda, c.saver.env_gae_lambda),
            (CUSTOM_SAVER_GAE_LAMBDA, 1.0)
        );
        assert_eq!(paper.saver.gae_lambda, 1.0);
        let a2c = recommended(&custom, Algo::A2c, 1);
        assert_eq!((a2c.gamma, a2c.rollout), (0.99, 8));
        assert!(!a2c.complete_at_success);
        assert!(!a2c.lr_decay);
        assert!(!RunConfig::paper(&custom, Algo::Saver, 1).lr_decay);
        assert!(!RunConfig::paper(&custom, Algo::Saver, 1).complete_at_success);
        assert_eq!(
            RunConfig::paper(&custom, Algo::Saver, 1).saver.pcpn_tune_lr,
            0.0
        );
        validate(&c).unwrap();
        assert_eq!(recommended(&custom, Algo::A2c, 1).saver.mu_raw_penalty, 0.0);
        for (kind, d) in [
            (EnvKind::Angle, 4),
            (EnvKind::Angle, 16),
            (EnvKind::Select, 4),
            (EnvKind::Arm, 2),
        ] {
            let c = recommended(&EnvSpec::new(kind, d).unwrap(), Algo::Saver, 1);
            assert_eq!(c.saver.mu_raw_penalty, 0.0, "{kind:?}");
            assert_eq!(c.saver.pcpn_tune_lr, 0.0, "{kind:?}");
            assert_eq!(
                (c.saver.pcpn_tune_rows, c.saver.quantiles),
                (0, 32),
                "{kind:?}"
            );
            assert_eq!((c.gamma, c.rollout), (0.99, 8), "{kind:?}");
            assert!(!c.complete_at_success, "{kind:?}");
            assert!(!c.lr_decay, "{kind:?}");
            assert_eq!(c.saver.minibatch_size, 0, "{kind:?}");
            assert_eq!((c.saver.epochs, c.saver.env_clip), (1, 0.0), "{kind:?}");
            assert_eq!(c.saver.obs_norm, ObsNorm::Off, "{kind:?}");
            assert_eq!(c.saver.gae_lambda, 1.0, "{kind:?}");
            assert_eq!(c.head.log_std_init, crate::config::LOG_STD_INIT, "{kind:?}");
            let mut asked = c.clone();
            asked.complete_at_success = true;
            let e = validate(&asked).unwrap_err().to_string();
            assert!(
                e.contains("complete_at_success") && e.contains("own reward"),
                "{e}"
            );
            // The paper's update on every preset: no env-return term, episodes that
            // end at success (asking to go on past it is refused).
            assert_eq!(c.saver.env_reward, 0.0, "{kind:?}");
            assert!(!c.continue_past_success, "{kind:?}");
            let mut past = c.clone();
            past.continue_past_success = true;
            let e = validate(&past).unwrap_err().to_string();
            assert!(
                e.contains("continue_past_success") && e.contains("ends its episodes"),
                "{e}"
            );
        }
    }
}
