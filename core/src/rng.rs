//! Seeded randomness: every random number of a run comes from a ChaCha8 stream derived
//! from the run seed, so runs repeat bit for bit (candle's own CPU RNG cannot be seeded).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// The RNG type used everywhere.
pub type SaverRng = ChaCha8Rng;

/// Streams derived from one seed; `stream` keeps the learner's, the actors' and the
/// pretraining's draws independent of each other.
pub fn rng_for(seed: u64, stream: u64) -> SaverRng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream);
    r
}

/// Stream ids, one per consumer of randomness.
pub mod streams {
    /// Weight initialisation of agent and critic.
    pub const INIT: u64 = 1;
    /// The learner's draws (SAVER's and QRRL's τ, PPO's minibatch shuffles).
    pub const LEARNER: u64 = 2;
    /// PCPN initialisation and pretraining samples.
    pub const PRETRAIN: u64 = 3;
    /// Held-out samples of the PCPN evaluation.
    pub const HELD_OUT: u64 = 4;
    /// `saver eval`'s episodes.
    pub const EVAL: u64 = 5;
    /// Actor `i` uses stream `ACTOR_BASE + i`.
    pub const ACTOR_BASE: u64 = 1_000;
}

/// Glorot (Xavier) uniform: U(-l, l) with l = sqrt(6 / (fan_in + fan_out)).
pub fn glorot_uniform(rng: &mut SaverRng, fan_in: usize, fan_out: usize) -> Vec<f32> {
    let limit = (6.0 / (fan_in + fan_out) as f64).sqrt() as f32;
    (0..fan_in * fan_out)
        .map(|_| rng.random_range(-limit..limit))
        .collect()
}

/// One standard normal draw.
pub fn normal(rng: &mut SaverRng) -> f32 {
    StandardNormal.sample(rng)
}

/// `n` uniform draws in [0, 1).
pub fn uniform01(rng: &mut SaverRng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random::<f32>()).collect()
}
