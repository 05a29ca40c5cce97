//! What the learner knows of an actor's envs between its rollouts: the steps and the
//! return of each env's running episode. A rollout's episode reports must agree with
//! them (a done flag is one episode of exactly the steps the learner counted), so a
//! client cannot forge the run's main metric, the mean episode length.

use saver_core::rollout::Rollout;
use saver_core::{CoreError, Result};

/// One actor session's running episodes, as the learner counts them.
#[derive(Clone, Debug, PartialEq)]
pub struct Ledger {
    /// The sequence number whose rollout continues where the counts stand.
    next_seq: u64,
    /// Steps and scalar return of each env's running episode (`None`: not known).
    envs: Vec<Option<(u32, f32)>>,
}

impl Ledger {
    /// A registration's ledger: its first rollout (sequence number 0) starts `n_envs`
    /// fresh episodes.
    pub fn fresh(n_envs: usize) -> Self {
        Self {
            next_seq: 0,
            envs: vec![Some((0, 0.0)); n_envs],
        }
    }

    /// A resumed actor's ledger: its next rollout is `next_seq`, its envs' running
    /// episodes are `running` (steps, return).
    pub fn resumed(next_seq: u64, running: &[(u32, f32)]) -> Self {
        Self {
            next_seq,
            envs: running.iter().map(|&r| Some(r)).collect(),
        }
    }

    /// Envs it counts.
    pub fn n_envs(&self) -> usize {
        self.envs.len()
    }

    /// Checks the episode reports of `r` (validated: one episode per done flag, in the
    /// order of the flags) and returns the ledger after it and, per episode, whether
    /// its length was verified (an episode that started before a gap in the sequence
    /// numbers cannot be, and does not count in the metrics).
    ///
    /// Every end that is not a success is the step limit (`max_len` steps); a verified
    /// episode has exactly the steps counted and their summed reward as its return.
    pub fn check(&self, r: &Rollout, max_len: u32) -> Result<(Ledger, Vec<bool>)> {
        let (e, n) = (r.n_envs, r.n_steps);
        let d = r.vector_reward.len() / (e * n).max(1);
        let continues = r.seq == self.next_seq && self.envs.len() == e;
        let mut envs = Vec::with_capacity(e);
        let mut verified = Vec::with_capacity(r.episodes.len());
        let mut k = 0;
        for i in 0..e {
            let mut run = if continues { self.envs[i] } else { None };
            for t in 0..n {
                let s = i * n + t;
                if let Some((steps, ret)) = &mut run {
                    *steps += 1;
                    *ret += r.vector_reward[s * d..(s + 1) * d].iter().sum::<f32>();
                }
                if !r.done[s] {
                    continue;
                }
                let ep = &r.episodes[k];
                k += 1;
                let bad = |why: String| {
                    Err(CoreError::Data(format!(
                        "episode of env {i} ending at step {t}: {why}"
                    )))
                };
                if ep.length == 0 || ep.length > max_len {
                    return bad(format!("length {} is not in 1..={max_len}", ep.length));
                }
                if !ep.success && ep.length != max_len {
                    return bad(format!(
                        "an episode that ends without success ends at the step limit \
                         {max_len}, not after {} steps",
                        ep.length
                    ));
                }
                if r.timeouts.binary_search(&(s as u32)).is_ok() && ep.success {
                    return bad("a timeout is no success".into());
                }
                match run {
                    Some((steps, ret)) => {
                        if ep.length != steps {
                            return bad(format!(
                                "length {} but the learner counted {steps} steps",
                                ep.length
                            ));
                        }
                        if (ep.ret - ret).abs() > 1e-3 * (1.0 + ret.abs()) {
                            return bad(format!("return {} but its rewards sum to {ret}", ep.ret));
                        }
                        verified.push(true);
                    }
                    None => {
                        // Started before what the learner saw: at least the steps here.
                        if ep.length < t as u32 + 1 {
                            return bad(format!(
                                "length {} but {} steps of it are in this rollout",
                                ep.length,
                                t + 1
                            ));
                        }
                        verified.push(false);
                    }
                }
                run = Some((0, 0.0));
            }
            envs.push(run);
        }
        Ok((
            Ledger {
                next_seq: r.seq.saturating_add(1),
                envs,
            },
            verified,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use saver_core::rollout::Episode;

    /// One env, `n` steps, reward 0.25 per step (d = 1), done at the given steps.
    fn rollout(seq: u64, n: usize, done_at: &[usize], episodes: &[(u32, bool, f32)]) -> Rollout {
        let mut done = vec![false; n];
        for &t in done_at {
            done[t] = true;
        }
        Rollout {
            actor_id: 0,
            session: 1,
            seq,
            policy_version: 0,
            n_envs: 1,
            n_steps: n,
            obs: vec![0.0; n + 1],
            payload: vec![0.0; 2 * n],
            actions: vec![0.0; n],
            state_delta: vec![0.25; n],
            vector_reward: vec![0.25; n],
            done,
            timeouts: vec![],
            timeout_obs: vec![],
            episodes: episodes
                .iter()
                .map(|&(length, success, ret)| Episode {
                    actor_id: 0,
                    length,
                    success,
                    ret,
                    verified: true,
                })
                .collect(),
            actor_state: None,
        }
    }

    #[test]
    fn lengths_are_counted_across_rollouts_and_forged_ones_refused() {
        let l = Ledger::fresh(1);
        // Rollout 0: no end (4 steps). Rollout 1: the episode ends at its step 2, so
        // it is 4 + 3 = 7 steps long with return 7 · 0.25 = 1.75.
        let (l, v) = l.check(&rollout(0, 4, &[], &[]), 1000).unwrap();
        assert!(v.is_empty());
        let (l2, v) = l
            .check(&rollout(1, 4, &[2], &[(7, true, 1.75)]), 1000)
            .unwrap();
        assert_eq!(v, vec![true]);
        // A forged length of 1 (the attack that moved the mean from 990 to 1), a
        // wrong return, a failure before the limit: refused.
        for forged in [(1, true, 1.75), (7, true, 0.25), (7, false, 1.75)] {
            let e = l.check(&rollout(1, 4, &[2], &[forged]), 1000).unwrap_err();
            assert!(e.to_string().contains("env 0 ending at step 2"), "{e}");
        }
        // After the end the count starts again: rollout 2 ends at step 0 → 1 + 1 = 2.
        let (_, v) = l2
            .check(&rollout(2, 4, &[0], &[(2, true, 0.5)]), 1000)
            .unwrap();
        assert_eq!(v, vec![true]);
    }

    #[test]
    fn after_a_gap_an_episode_is_bounded_but_not_counted() {
        // Sequence 5 after 0: the envs ran unseen in between.
        let l = Ledger::fresh(1);
        let (_, v) = l
            .check(&rollout(5, 4, &[2], &[(40, true, 3.0)]), 1000)
            .unwrap();
        assert_eq!(v, vec![false]);
        // Still no shorter than its steps in this rollout (3).
        assert!(l
            .check(&rollout(5, 4, &[2], &[(2, true, 0.5)]), 1000)
            .is_err());
        // The step limit: a timeout of 1000 steps is no success.
        let mut r = rollout(5, 4, &[3], &[(1000, true, 0.0)]);
        r.timeouts = vec![3];
        assert!(l.check(&r, 1000).is_err());
        r.episodes[0].success = false;
        assert!(l.check(&r, 1000).is_ok());
    }
}
