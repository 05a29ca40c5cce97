//! The run's policy files, for any client to load (`saver eval`, `saver_actor.Policy`):
//! `policy.safetensors`, the newest weights, written with every checkpoint; and, where
//! the learner can evaluate a policy, `best.safetensors`, the weights whose
//! deterministic evaluation returned the most so far, with every evaluation in
//! `eval.csv`. Both are self-describing weights files (format saver-policy/1) written
//! atomically.

use saver_core::link::PolicyWeights;
use saver_core::{CoreError, Result};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The newest weights.
pub const POLICY_FILE: &str = "policy.safetensors";
/// The best weights by evaluation.
pub const BEST_FILE: &str = "best.safetensors";
/// Every evaluation.
pub const EVAL_CSV: &str = "eval.csv";

/// How a policy did in an evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Evaluation {
    /// Mean undiscounted scalar return per episode.
    pub mean_return: f32,
    /// Share of episodes that reached the goal.
    pub success_rate: f32,
    /// Episodes run.
    pub episodes: u32,
}

/// Evaluates weights on the run's env (the same episode starts every time, so that
/// two versions are compared on equal terms).
pub type Evaluator = Box<dyn FnMut(Arc<PolicyWeights>) -> Result<Evaluation> + Send>;

/// Writes the policy files of one run folder.
pub struct PolicyFiles {
    dir: PathBuf,
    /// What the weights are (`saver_core::link::weights_metadata`).
    about: HashMap<String, String>,
    evaluator: Option<Evaluator>,
    /// The best mean return so far (read back from best.safetensors on a resume).
    best: Option<f32>,
    /// The versions last written to policy.safetensors and last evaluated: a run
    /// whose end falls on a checkpoint or an evaluation does neither twice.
    newest: Option<u64>,
    evaluated: Option<u64>,
}

fn io(what: &str, path: &Path, e: std::io::Error) -> CoreError {
    CoreError::Checkpoint(format!("{what} {}: {e}", path.display()))
}

impl PolicyFiles {
    /// The policy files of `dir` for weights described by `about`; without an
    /// evaluator there is no best.safetensors.
    pub fn new(dir: &Path, about: HashMap<String, String>, evaluator: Option<Evaluator>) -> Self {
        let best = std::fs::File::open(dir.join(BEST_FILE))
            .ok()
            .and_then(|f| saver_proto::read_metadata(f).ok())
            .and_then(|m| m.get("eval_return")?.parse().ok());
        Self {
            dir: dir.to_path_buf(),
            about,
            evaluator,
            best,
            newest: None,
            evaluated: None,
        }
    }

    fn write(&self, file: &str, w: &PolicyWeights, extra: &[(&str, String)]) -> Result<()> {
        let mut meta = self.about.clone();
        meta.insert("version".into(), w.version.to_string());
        for (k, v) in extra {
            meta.insert((*k).into(), v.clone());
        }
        saver_core::checkpoint::save(&self.dir.join(file), &w.tensors, &meta)?;
        Ok(())
    }

    /// Writes policy.safetensors (unless it holds this version already).
    pub fn save_newest(&mut self, w: &PolicyWeights) -> Result<()> {
        if self.newest != Some(w.version) {
            self.write(POLICY_FILE, w, &[])?;
            self.newest = Some(w.version);
        }
        Ok(())
    }

    /// Evaluates `w` (at `steps` env steps), adds a row to eval.csv and, when it
    /// returned more than every evaluation before, writes best.safetensors. Returns
    /// the evaluation, if there is an evaluator and this version was not evaluated
    /// just before.
    pub fn evaluate(&mut self, steps: u64, w: Arc<PolicyWeights>) -> Result<Option<Evaluation>> {
        let version = w.version;
        let Some(evaluate) = self
            .evaluator
            .as_mut()
            .filter(|_| self.evaluated != Some(version))
        else {
            return Ok(None);
        };
        self.evaluated = Some(version);
        let e = evaluate(w.clone())?;
        let better = self.best.is_none_or(|b| e.mean_return > b);
        if better {
            self.best = Some(e.mean_return);
            self.write(
                BEST_FILE,
                &w,
                &[
                    ("eval_return", e.mean_return.to_string()),
                    ("eval_success_rate", e.success_rate.to_string()),
                    ("eval_episodes", e.episodes.to_string()),
                    ("eval_steps", steps.to_string()),
                ],
            )?;
        }
        let path = self.dir.join(EVAL_CSV);
        let new = !path.exists();
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| io("opening", &path, e))?;
        let mut text = String::new();
        if new {
            text.push_str("steps,updates,episodes,mean_return,success_rate,best\n");
        }
        text.push_str(&format!(
            "{steps},{version},{},{},{},{}\n",
            e.episodes, e.mean_return, e.success_rate, better as u8
        ));
        f.write_all(text.as_bytes())
            .map_err(|e| io("writing", &path, e))?;
        Ok(Some(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use saver_proto::NamedTensor;

    fn weights(version: u64, x: f32) -> Arc<PolicyWeights> {
        Arc::new(PolicyWeights {
            version,
            tensors: vec![NamedTensor {
                name: "agent.x".into(),
                shape: vec![1],
                data: vec![x],
            }],
        })
    }

    /// An evaluator that scores the weights by their one value: best.safetensors holds
    /// the highest-scoring version (2, of scores 1, 3, 2), eval.csv every evaluation,
    /// and a new PolicyFiles on the folder (a resume) knows the best so far.
    #[test]
    fn best_keeps_the_highest_evaluation_across_a_resume() {
        let dir = std::env::temp_dir().join(format!("saver-best-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let score: Evaluator = Box::new(|w| {
            Ok(Evaluation {
                mean_return: w.tensors[0].data[0],
                success_rate: 0.5,
                episodes: 4,
            })
        });
        let about = HashMap::from([("format".to_string(), "saver-policy/1".to_string())]);
        let mut files = PolicyFiles::new(&dir, about.clone(), Some(score));
        for (v, x) in [(1, 1.0), (2, 3.0), (3, 2.0)] {
            files.evaluate(v * 100, weights(v, x)).unwrap();
            files.save_newest(&weights(v, x)).unwrap();
        }
        // The run's end on the version just evaluated: no second row.
        assert_eq!(files.evaluate(300, weights(3, 2.0)).unwrap(), None);
        let read = |f: &str| {
            let (t, m) = saver_proto::decode(&std::fs::read(dir.join(f)).unwrap()).unwrap();
            (t[0].data[0], m)
        };
        let (best, meta) = read(BEST_FILE);
        assert_eq!((best, meta["version"].as_str()), (3.0, "2"));
        assert_eq!(meta["eval_steps"], "200");
        assert_eq!(meta["format"], "saver-policy/1");
        assert_eq!(read(POLICY_FILE).0, 2.0);
        let csv = std::fs::read_to_string(dir.join(EVAL_CSV)).unwrap();
        assert_eq!(
            csv,
            "steps,updates,episodes,mean_return,success_rate,best\n\
             100,1,4,1,0.5,1\n200,2,4,3,0.5,1\n300,3,4,2,0.5,0\n"
        );
        // Resumed: 2.5 is not above the 3 kept; 4 is.
        let score: Evaluator = Box::new(|w| {
            Ok(Evaluation {
                mean_return: w.tensors[0].data[0],
                success_rate: 1.0,
                episodes: 4,
            })
        });
        let mut files = PolicyFiles::new(&dir, about, Some(score));
        files.evaluate(400, weights(4, 2.5)).unwrap();
        assert_eq!(read(BEST_FILE).0, 3.0);
        files.evaluate(500, weights(5, 4.0)).unwrap();
        assert_eq!(read(BEST_FILE).0, 4.0);
        std::fs::remove_dir_all(dir).ok();
    }
}
