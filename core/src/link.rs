//! The narrow interface between an actor and a learner. Everything an actor needs:
//! register, get weights of at least some version, hand over a rollout. The embedded
//! run implements it in-process; the gRPC client implements it over the network.

use crate::acting::PolicyFamily;
pub use crate::acting::PolicyWeights;
use crate::config::{Algo, Mode, RunConfig};
use crate::env::EnvSpec;
use crate::rollout::Rollout;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

/// What an actor says about itself when it registers.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Human-readable name (host, pid) for logs.
    pub name: String,
    /// The client's own random number, for its logs; the learner issues the session
    /// itself ([`Assignment::session`]).
    pub session: u64,
    /// How many env instances this actor steps per rollout.
    pub n_envs: u32,
}

/// What the learner answers.
#[derive(Clone, Debug)]
pub struct Assignment {
    /// Dense id; sync batches are ordered by it and actor seeds derive from it.
    pub actor_id: u32,
    /// The learner's secret for this registration: every rollout and the rollout
    /// stream carry it; no other client can guess it.
    pub session: u64,
    /// What the actor needs of the run.
    pub settings: ActorSettings,
}

/// What an actor of a run needs to know of it (RegisterReply.settings on the wire).
#[derive(Clone, Debug)]
pub struct ActorSettings {
    /// The algorithm (for logs; the policy family is what acting needs).
    pub algo: Algo,
    /// Sync: one rollout per version; async: act on with the newest weights.
    pub mode: Mode,
    /// Steps n per rollout.
    pub rollout: u32,
    /// Base seed (actor i draws from stream `ACTOR_BASE + i`).
    pub seed: u64,
    /// The env's step limit.
    pub max_episode_steps: u32,
    /// Complete the progress reward at success ([`RunConfig::complete_at_success`]):
    /// what a custom env's actor does; preset actors have nothing to complete.
    pub complete_at_success: bool,
    /// Go on past success ([`RunConfig::continue_past_success`]).
    pub continue_past_success: bool,
    /// The environment.
    pub env: EnvSpec,
    /// The behaviour policy: how to act and what each step records.
    pub policy: Arc<dyn PolicyFamily>,
}

/// Format tag of a self-describing policy weights file.
pub const POLICY_FORMAT: &str = "saver-policy/1";

/// What a weights file of `config`'s run says about itself (its safetensors
/// metadata, besides the version): enough for a client in any language to act with
/// it — the env (spec with layout and bounds), the algorithm, the policy family with
/// its parameters and architecture, and the PCPN the run used.
pub fn weights_metadata(config: &RunConfig) -> HashMap<String, String> {
    let s = ActorSettings::of(config);
    let mut m = HashMap::from([
        ("format".to_string(), POLICY_FORMAT.to_string()),
        ("algo".to_string(), s.algo.name().to_string()),
        ("env".to_string(), s.env.to_string()),
        ("env_spec".to_string(), json(&s.env)),
        ("layout".to_string(), json(&s.env.layout())),
        ("policy_family".to_string(), s.policy.name().to_string()),
        ("policy_params".to_string(), json(&s.policy.params())),
        ("payload".to_string(), s.policy.payload_layout()),
        ("architecture".to_string(), s.policy.architecture()),
        (
            "max_episode_steps".to_string(),
            s.max_episode_steps.to_string(),
        ),
    ]);
    if let Some(sha) = &config.pcpn_sha256 {
        m.insert("pcpn_sha256".to_string(), sha.clone());
    }
    m
}

fn json<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_string(v).unwrap_or_default()
}

/// Reads back what [`weights_metadata`] wrote: the env, the algorithm, the policy
/// family with its parameters (a null parameter, JSON's missing infinity, is no
/// bound: −∞ for a lower one, +∞ otherwise) and the step limit, as the settings of an
/// actor that acts with the weights (sync, rollouts of 1, seed 0: evaluation's).
pub fn settings_from_metadata(meta: &HashMap<String, String>) -> crate::Result<ActorSettings> {
    use crate::CoreError;
    let get = |k: &str| {
        meta.get(k)
            .ok_or_else(|| CoreError::Checkpoint(format!("its metadata has no {k:?}")))
    };
    let bad = |k: &str, e: &dyn std::fmt::Display| CoreError::Checkpoint(format!("{k}: {e}"));
    let env: EnvSpec = serde_json::from_str(get("env_spec")?).map_err(|e| bad("env_spec", &e))?;
    let params: std::collections::BTreeMap<String, Option<f64>> =
        serde_json::from_str(get("policy_params")?).map_err(|e| bad("policy_params", &e))?;
    let params = params
        .into_iter()
        .map(|(k, v)| {
            let none = if k.ends_with("_min") {
                f64::NEG_INFINITY
            } else {
                f64::INFINITY
            };
            (k, v.unwrap_or(none))
        })
        .collect();
    let policy = crate::nets::family_from_wire(get("policy_family")?, env.layout(), &params)?;
    let max_episode_steps = get("max_episode_steps")?
        .parse()
        .map_err(|e| bad("max_episode_steps", &e))?;
    Ok(ActorSettings {
        algo: Algo::parse(get("algo")?)?,
        mode: Mode::Sync,
        rollout: 1,
        seed: 0,
        max_episode_steps,
        complete_at_success: false,
        continue_past_success: false,
        env,
        policy,
    })
}

impl ActorSettings {
    /// The settings of `config`'s actors.
    pub fn of(config: &RunConfig) -> Self {
        Self {
            algo: config.algo,
            mode: config.mode,
            rollout: config.rollout,
            seed: config.seed,
            max_episode_steps: config.max_episode_steps,
            complete_at_success: config.complete_at_success,
            continue_past_success: config.continue_past_success,
            env: config.env.clone(),
            policy: crate::algo::policy_family(config),
        }
    }
}

/// Why a link call failed.
#[derive(Clone, Debug, thiserror::Error)]
pub enum LinkError {
    /// The learner is gone, unreachable or restarting: the actor should reconnect.
    #[error("learner closed: {0}")]
    Closed(String),
    /// The run is over (every step trained): the actor should stop.
    #[error("run finished: {0}")]
    Finished(String),
    /// The learner refused this request as malformed; the message says why.
    #[error("rejected by the learner: {0}")]
    Rejected(String),
    /// The request does not fit the learner's state: unknown actor or session, a
    /// replayed sequence number, a policy version from the future.
    #[error("refused by the learner: {0}")]
    Mismatch(String),
    /// The request is over a size cap.
    #[error("too large for the learner: {0}")]
    TooLarge(String),
    /// The learner is up but waits (for its PCPN) before it serves: the actor should
    /// keep asking, with no deadline; the message says how far the wait is.
    #[error("the learner {0}")]
    Waiting(String),
}

/// The actor side of the actor–learner interface.
pub trait LearnerLink: Send {
    /// Registers and learns the actor id and run config.
    fn register(&mut self, reg: &Registration) -> Result<Assignment, LinkError>;
    /// Blocks until weights of at least `min_version` exist; returns the newest.
    fn weights(&mut self, min_version: u64) -> Result<Arc<PolicyWeights>, LinkError>;
    /// Waits at most `wait` for weights of at least `min_version`, then returns the
    /// newest there are (async actors pace themselves with it).
    fn weights_within(
        &mut self,
        min_version: u64,
        wait: Duration,
    ) -> Result<Arc<PolicyWeights>, LinkError>;
    /// Hands a rollout to the learner.
    fn push(&mut self, rollout: Rollout) -> Result<(), LinkError>;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::env::EnvKind;

    /// What the weights metadata says reads back as the run's actor settings: the
    /// env, the algorithm, the family's parameters (an unbounded μ, written as null,
    /// back as +∞) and the step limit.
    #[test]
    fn weights_metadata_reads_back() {
        let env = EnvSpec::new(EnvKind::Select, 3).unwrap();
        let config = RunConfig::paper(&env, Algo::A2c, 0);
        let back = settings_from_metadata(&weights_metadata(&config)).unwrap();
        let want = ActorSettings::of(&config);
        assert_eq!((back.algo, &back.env), (want.algo, &want.env));
        assert_eq!(back.max_episode_steps, want.max_episode_steps);
        assert_eq!(back.policy.name(), want.policy.name());
        assert_eq!(back.policy.params(), want.policy.params());
        let mut missing = weights_metadata(&config);
        missing.remove("policy_family");
        let e = settings_from_metadata(&missing).err().unwrap().to_string();
        assert!(e.contains("policy_family"), "{e}");
    }
}
