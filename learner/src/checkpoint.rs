//! The learner's checkpoint: what it holds, writing it atomically, and resuming a run
//! from it.

use crate::metrics::EpisodeWindow;
use saver_core::algo::Algorithm;
use saver_core::checkpoint;
use saver_core::config::RunConfig;
use saver_core::rollout::ActorState;
use saver_core::{CoreError, Result};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// Saved in-process actors by id (sync runs), so that a resumed run continues exactly.
pub type ActorStates = BTreeMap<u32, ActorState>;

/// Counters saved in checkpoints.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counters {
    /// Weights version (updates done).
    pub version: u64,
    /// Env steps trained on.
    pub steps: u64,
    /// Episodes finished.
    pub episodes: u64,
    /// Milliseconds of training before this process (a resumed run's rates go on from
    /// them).
    pub wall_ms: u64,
}

/// Where a run stands besides its algorithm: what a checkpoint saves with it and a
/// resumed run starts from.
#[derive(Clone, Debug, Default)]
pub struct RunState {
    /// Counters.
    pub counters: Counters,
    /// Saved in-process actors.
    pub actors: ActorStates,
    /// The last episodes, so that the 100-episode mean goes on where it was.
    pub window: EpisodeWindow,
}

/// Name of the learner's checkpoint in its run folder.
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";

/// Loads `run_dir`'s checkpoint into `algo` if there is one and returns its counters,
/// saved actors and episode window (`None`: no checkpoint, a fresh run). A checkpoint
/// of another config is an error: resuming it would mix two runs.
pub fn resume(
    run_dir: &Path,
    config: &RunConfig,
    algo: &mut dyn Algorithm,
) -> Result<Option<RunState>> {
    let path = run_dir.join(CHECKPOINT_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let c = checkpoint::load(&path)?;
    let meta = |k: &str| {
        c.meta.get(k).cloned().ok_or_else(|| {
            CoreError::Checkpoint(format!("{}: no {k:?} in its metadata", path.display()))
        })
    };
    let num = |k: &str| -> Result<u128> {
        meta(k)?.parse().map_err(|_| {
            CoreError::Checkpoint(format!("{}: {k:?} is not a number", path.display()))
        })
    };
    let format = meta("format")?;
    if format != CHECKPOINT_FORMAT {
        return Err(CoreError::Checkpoint(format!(
            "{} is a checkpoint of format {format:?}; this SAVER reads {CHECKPOINT_FORMAT:?}",
            path.display()
        )));
    }
    same_settings(&path, &meta("config")?, config)?;
    let tensors = checkpoint::to_candle(&c.tensors, &saver_core::device())?;
    // The algorithm's numbers are stored as `algo.<name>` entries of the metadata.
    let numbers = c
        .meta
        .iter()
        .filter_map(|(k, v)| Some((k.strip_prefix(ALGO_PREFIX)?.to_string(), v)))
        .map(|(k, v)| {
            v.parse().map(|n| (k.clone(), n)).map_err(|_| {
                CoreError::Checkpoint(format!(
                    "{}: {ALGO_PREFIX}{k} is not a number",
                    path.display()
                ))
            })
        })
        .collect::<Result<_>>()?;
    algo.restore_state(&|n| tensors.get(n).cloned(), &numbers)?;
    let counters = Counters {
        version: num("version")? as u64,
        steps: num("steps")? as u64,
        episodes: num("episodes")? as u64,
        // Checkpoints before wall_ms existed resume with the clock at 0.
        wall_ms: c
            .meta
            .get("wall_ms")
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
    };
    let window = EpisodeWindow::from_saved(
        c.tensors.iter().find(|t| t.name == "window.all"),
        c.tensors.iter().find(|t| t.name == "window.actor0"),
        c.meta
            .get("window.total")
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
        c.meta
            .get("window.successes")
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
    );
    // Saved actors: `actor.<id>.state` rows, `actor.<id>.rng` and `.seq` metadata.
    // Rows are [env snapshot, observation, steps, return]: the snapshot's length is
    // what the row leaves after the observation (the learner builds no env).
    let obs_len = config.env.layout().obs_dim;
    let mut actors = ActorStates::new();
    for t in &c.tensors {
        let Some(id) = t
            .name
            .strip_prefix("actor.")
            .and_then(|r| r.strip_suffix(".state"))
        else {
            continue;
        };
        let bad = || CoreError::Checkpoint(format!("{}: bad saved actor {id}", path.display()));
        let id: u32 = id.parse().map_err(|_| bad())?;
        let rng = num(&format!("actor.{id}.rng"))?;
        let seq = num(&format!("actor.{id}.seq"))? as u64;
        let env_len = t.shape.get(1).map_or(0, |w| w.saturating_sub(obs_len + 2));
        let state = ActorState::from_rows(&t.shape, &t.data, env_len, obs_len, rng, seq)?;
        actors.insert(id, state);
    }
    Ok(Some(RunState {
        counters,
        actors,
        window,
    }))
}

/// Refuses `run_dir` when its checkpoint belongs to a run of other settings (no
/// checkpoint: a fresh run, accepted). Reads only the checkpoint's header; call it
/// before writing anything there. Returns the weights sha256 of the PCPN the saved run
/// used, which its continuation must use again.
pub fn check_settings(run_dir: &Path, config: &RunConfig) -> Result<Option<String>> {
    let path = run_dir.join(CHECKPOINT_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let unreadable = |e: String| CoreError::Checkpoint(format!("{}: {e}", path.display()));
    let file = std::fs::File::open(&path).map_err(|e| unreadable(e.to_string()))?;
    let meta = saver_proto::read_metadata(std::io::BufReader::new(file))
        .map_err(|e| unreadable(e.to_string()))?;
    same_settings(&path, meta.get("config").map_or("", String::as_str), config)
}

/// Every setting must match but the length of the run (resuming with more steps
/// trains on) and a PCPN not chosen yet (the saved run's is then the one to use).
/// Returns the saved run's PCPN sha256.
fn same_settings(path: &Path, saved_json: &str, config: &RunConfig) -> Result<Option<String>> {
    let saved = RunConfig::from_json(saved_json).map_err(|e| {
        CoreError::Checkpoint(format!(
            "{}: its settings are unreadable here ({e}): a checkpoint of another SAVER \
             version; nothing in that folder was changed. Start this run in another folder \
             (--out DIR)",
            path.display()
        ))
    })?;
    {
        let mut saved = saved;
        let pcpn = saved.pcpn_sha256.clone();
        saved.steps = config.steps;
        if config.pcpn_sha256.is_none() {
            saved.pcpn_sha256 = None;
        }
        if saved.hash() == config.hash() {
            return Ok(pcpn);
        }
    }
    let run_dir = path.parent().unwrap_or(Path::new("."));
    Err(CoreError::Checkpoint(format!(
        "{} belongs to a run with other settings; nothing in that folder was changed. \
         Resume it with its own settings (`--config {}`; only --steps may change), or \
         start this run in another folder (--out DIR; with docker compose, another \
         project name (-p NAME) or `down -v` to delete the old run's volume)",
        path.display(),
        run_dir.join("config.toml").display()
    )))
}

const CHECKPOINT_FORMAT: &str = "saver-learner-checkpoint/2";
/// Prefix of the algorithm's numbers ([`saver_core::algo::AlgoState::numbers`]) in the
/// checkpoint's metadata.
const ALGO_PREFIX: &str = "algo.";

/// Writes the learner's checkpoint to `path` atomically: every tensor of `algo` and
/// its optimiser, the counters, the tau-stream position, the saved actors, the config
/// and its hash.
pub fn save(
    path: &Path,
    algo: &dyn Algorithm,
    c: &Counters,
    actors: &ActorStates,
    window: &EpisodeWindow,
    config: &RunConfig,
) -> Result<()> {
    let state = algo.save_state()?;
    let mut tensors = checkpoint::to_named_all(&state.tensors)?;
    tensors.extend(window.to_saved());
    let mut meta = HashMap::from([
        ("format".to_string(), CHECKPOINT_FORMAT.to_string()),
        ("version".to_string(), c.version.to_string()),
        ("steps".to_string(), c.steps.to_string()),
        ("episodes".to_string(), c.episodes.to_string()),
        ("wall_ms".to_string(), c.wall_ms.to_string()),
        ("window.total".to_string(), window.total.to_string()),
        ("window.successes".to_string(), window.successes.to_string()),
        (
            "config".to_string(),
            serde_json::to_string(config).unwrap_or_default(),
        ),
        ("config_hash".to_string(), config.hash()),
    ]);
    for (k, v) in &state.numbers {
        meta.insert(format!("{ALGO_PREFIX}{k}"), v.to_string());
    }
    for (id, a) in actors {
        let (shape, data) = a.to_rows();
        tensors.push(saver_proto::NamedTensor {
            name: format!("actor.{id}.state"),
            shape,
            data,
        });
        meta.insert(format!("actor.{id}.rng"), a.rng_word_pos.to_string());
        meta.insert(format!("actor.{id}.seq"), a.seq.to_string());
    }
    checkpoint::save(path, &tensors, &meta)?;
    Ok(())
}
