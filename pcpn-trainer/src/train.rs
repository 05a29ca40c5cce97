//! Pretraining a PCPN for an env spec, with divergence detection and a held-out
//! quantile loss on fresh samples.

use crate::samples::{SampleHub, SHUFFLE};
use candle_core::Device;
use saver_core::config::{PretrainConfig, SampleDistribution, PRETRAIN_EVAL_BATCHES};
use saver_core::env::EnvSpec;
use saver_core::nets::Pcpn;
use saver_core::pretrain::{EnvSampler, Pretrainer, SampleSource};
use saver_core::rng::streams;
use saver_core::{checkpoint, CoreError};
use std::collections::HashMap;
use std::sync::Arc;

/// What pretraining reports after each batch.
pub struct PretrainProgress {
    /// Batches done.
    pub batch: u64,
    /// Of.
    pub batches: u64,
    /// Training loss of this batch.
    pub loss: f32,
}

/// The outcome of pretraining.
pub struct PretrainReport {
    /// The frozen PCPN.
    pub pcpn: Pcpn,
    /// Its tensors, ready to save.
    pub tensors: Vec<saver_proto::NamedTensor>,
    /// Metadata for the file.
    pub meta: HashMap<String, String>,
    /// Held-out quantile loss before training.
    pub initial_loss: f32,
    /// Held-out quantile loss after training.
    pub held_out_loss: f32,
}

/// Metadata key of the pretraining settings (JSON of [`PretrainConfig`]).
pub const PRETRAIN_META: &str = "pretrain";

/// Stream of the held-out sample source (apart from training and tau draws).
const HELD_OUT_SOURCE: u64 = 5;
/// How often (in batches) the training loss is checked for divergence.
const CHECK_EVERY: u64 = 50;
/// A loss this many times the initial held-out loss counts as diverged.
const DIVERGED_FACTOR: f32 = 100.0;

/// Pretrains a PCPN for `spec` per `p`; fails on divergence. A built-in env gives its
/// own samples (every entry point — `saver train`, `saver pretrain`, the Pretrain RPC
/// — comes here, so the same settings give the same weights bit for bit); a custom
/// env's come from the actors connected to `streamed` (refused without one), the
/// first 16 batches of them held out.
pub fn pretrain_pcpn(
    spec: &EnvSpec,
    p: &PretrainConfig,
    dev: &Device,
    streamed: Option<&Arc<SampleHub>>,
    progress: &mut dyn FnMut(&PretrainProgress),
) -> Result<PretrainReport, CoreError> {
    p.validate()?;
    p.check_env(spec)?;
    match p.samples {
        SampleDistribution::Reset => {
            let source = Box::new(EnvSampler::new(spec, p.seed, streams::PRETRAIN)?);
            let mut held_out = EnvSampler::new(spec, p.seed, HELD_OUT_SOURCE)?;
            pretrain_from(source, &mut held_out, p, dev, progress)
        }
        SampleDistribution::Walk => {
            let hub = streamed.ok_or_else(|| {
                CoreError::Config(format!(
                    "{spec} is a custom env: its PCPN is pretrained from samples its actors \
                     stream, which a pcpn-trainer gathers (`saver pcpn-trainer`; the learner \
                     with --pcpn http://HOST:PORT and the actors with --pcpn-samples at the \
                     same address), or give the learner a PCPN file with --pcpn FILE"
                ))
            })?;
            let held = PRETRAIN_EVAL_BATCHES * p.batch_size;
            let total = p.streamed_total();
            let mut source = hub.source(spec, total, p.seed)?;
            let mut held_out = source.held_out(held)?;
            let (train, how): (Box<dyn SampleSource>, String) = match p.walk_samples {
                0 => (
                    Box::new(source),
                    format!("the rest read once through a shuffle buffer of {SHUFFLE}"),
                ),
                n => (
                    Box::new(source.into_pool(n as usize)?),
                    format!("each batch drawn from the other {n} at random, with replacement"),
                ),
            };
            let mut report = pretrain_from(train, &mut held_out, p, dev, progress)?;
            report.meta.insert(
                "samples".into(),
                format!(
                    "{total} transitions streamed by actors (walks: each step mu ~ U(-1, 1), \
                     sigma ~ U(0, 1), a ~ N(mu, sigma^2), from the env's reset to its episode \
                     end); the first {held} held out, {how}"
                ),
            );
            Ok(report)
        }
    }
}

/// Pretrains a PCPN on samples from `source` (any [`SampleSource`]), reporting its
/// quantile loss on `held_out` before and after.
pub fn pretrain_from(
    source: Box<dyn SampleSource>,
    held_out: &mut dyn SampleSource,
    p: &PretrainConfig,
    dev: &Device,
    progress: &mut dyn FnMut(&PretrainProgress),
) -> Result<PretrainReport, CoreError> {
    let layout = source.layout();
    let mut trainer = Pretrainer::new(source, p, dev)?;
    let initial_loss = trainer.evaluate(held_out, PRETRAIN_EVAL_BATCHES, p.seed)?;
    let mut recent = 0.0f32;
    for batch in 1..=p.batches {
        let loss = trainer.step()?;
        recent = if batch == 1 {
            loss
        } else {
            0.98 * recent + 0.02 * loss
        };
        if batch % CHECK_EVERY == 0 && recent > DIVERGED_FACTOR * initial_loss {
            return Err(CoreError::Diverged(format!(
                "PCPN pretraining: training loss {recent:.3e} after {batch} batches \
                 (held-out loss at start {initial_loss:.3e}); lower --pretrain-lr (now {})",
                p.lr
            )));
        }
        progress(&PretrainProgress {
            batch,
            batches: p.batches,
            loss,
        });
    }
    let held_out_loss = trainer.evaluate(held_out, PRETRAIN_EVAL_BATCHES, p.seed)?;
    if !held_out_loss.is_finite() || held_out_loss >= initial_loss {
        return Err(CoreError::Diverged(format!(
            "PCPN pretraining failed: held-out quantile loss {held_out_loss:.3e} is not below \
             the untrained network's {initial_loss:.3e}; lower --pretrain-lr (now {}) or train longer",
            p.lr
        )));
    }
    let pcpn = trainer.frozen()?;
    let tensors = checkpoint::to_named_all(&pcpn.tensors()?)?;
    let meta = HashMap::from([
        (
            "architecture".to_string(),
            format!(
                "x[{}]->256->{}x128, cos(pi*i*tau) i=1..128, per-dim 128->64->1, relu",
                layout.pcpn_input_dim(),
                layout.aligned_dim
            ),
        ),
        (
            "layout".to_string(),
            serde_json::to_string(&layout).unwrap_or_default(),
        ),
        (
            PRETRAIN_META.to_string(),
            serde_json::to_string(p).unwrap_or_default(),
        ),
        (
            "initial_held_out_loss".to_string(),
            initial_loss.to_string(),
        ),
        ("held_out_loss".to_string(), held_out_loss.to_string()),
        (
            "held_out_batches".to_string(),
            PRETRAIN_EVAL_BATCHES.to_string(),
        ),
    ]);
    Ok(PretrainReport {
        pcpn,
        tensors,
        meta,
        initial_loss,
        held_out_loss,
    })
}
