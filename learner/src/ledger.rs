//! What the learner knows of an actor's envs between its rollouts: the steps, the
//! return and the last state-aligned position of each env's running episode. A
//! rollout's episode reports must agree with them (a done flag is one episode of
//! exactly the steps the learner counted), and its positions with its own state
//! changes (each step moves p by the Δp it reports, and a success ends within the
//! env's success radius), so a client cannot forge the run's main metrics, the mean
//! episode length and the success rate.

use saver_core::env::{EnvLayout, SuccessRule};
use saver_core::rollout::Rollout;
use saver_core::{CoreError, Result};

/// What every rollout of a run must agree with: the step limit, where p is in an
/// observation, and the success rule when the learner knows it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeRules {
    /// The step limit (`max_episode_steps`).
    pub max_len: u32,
    /// The env's layout (observation size, the aligned entries).
    pub layout: EnvLayout,
    /// When an episode succeeds (`None`: the env's own word, unchecked).
    pub success: Option<SuccessRule>,
    /// Episodes go on past success (`continue_past_success`): one that ends at the
    /// step limit inside the success box is a timeout and a success.
    pub continue_past_success: bool,
}

/// How far apart p + Δp and the p' a client reports may be: rounding of the client's
/// arithmetic (in f32 or f64), not a step.
fn tolerance(p: f32, q: f32) -> f32 {
    1e-5 * (1.0 + p.abs() + q.abs())
}

/// One actor session's running episodes, as the learner counts them.
#[derive(Clone, Debug, PartialEq)]
pub struct Ledger {
    /// The sequence number whose rollout continues where the counts stand.
    next_seq: u64,
    /// Steps and scalar return of each env's running episode (`None`: not known).
    envs: Vec<Option<(u32, f32)>>,
    /// The aligned position each env's last rollout ended at (`None`: not known).
    ends: Vec<Option<Vec<f32>>>,
}

impl Ledger {
    /// A registration's ledger: its first rollout (sequence number 0) starts `n_envs`
    /// fresh episodes.
    pub fn fresh(n_envs: usize) -> Self {
        Self {
            next_seq: 0,
            envs: vec![Some((0, 0.0)); n_envs],
            ends: vec![None; n_envs],
        }
    }

    /// A resumed actor's ledger: its next rollout is `next_seq`, its envs' running
    /// episodes are `running` (steps, return).
    pub fn resumed(next_seq: u64, running: &[(u32, f32)]) -> Self {
        Self {
            next_seq,
            envs: running.iter().map(|&r| Some(r)).collect(),
            ends: vec![None; running.len()],
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
    /// Every end that is not a success is the step limit (`rules.max_len` steps); a
    /// verified episode has exactly the steps counted and their summed reward as its
    /// return. Every step's p + Δp is the p' that follows it (the next observation, a
    /// timeout's final one), a rollout starts where the one before ended, and a
    /// success ends within the success rule's radius: so no episode is shorter than
    /// the distance from its start to the goal allows at max_change a step.
    pub fn check(&self, r: &Rollout, rules: &EpisodeRules) -> Result<(Ledger, Vec<bool>)> {
        let (e, n) = (r.n_envs, r.n_steps);
        let max_len = rules.max_len;
        let d = r.vector_reward.len() / (e * n).max(1);
        let continues = r.seq == self.next_seq && self.envs.len() == e;
        let motion = Motion::new(r, rules.layout);
        // Where the step in hand went, p + Δp (one buffer for the whole rollout).
        let mut reached = Vec::with_capacity(rules.layout.aligned_dim);
        let mut envs = Vec::with_capacity(e);
        let mut ends = Vec::with_capacity(e);
        let mut verified = Vec::with_capacity(r.episodes.len());
        let mut k = 0;
        for i in 0..e {
            let mut run = if continues { self.envs[i] } else { None };
            if let Some(end) = self
                .ends
                .get(i)
                .and_then(Option::as_ref)
                .filter(|_| continues)
            {
                motion.starts_at(i, end)?;
            }
            for t in 0..n {
                let s = i * n + t;
                motion.step(i, t, r.done[s], &mut reached)?;
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
                let timeout = r.timeouts.binary_search(&(s as u32)).is_ok();
                if (!ep.success || timeout) && ep.length != max_len {
                    return bad(format!(
                        "an episode that ends without success, or at a timeout, ends at \
                         the step limit \
                         {max_len}, not after {} steps",
                        ep.length
                    ));
                }
                if timeout && ep.success && !rules.continue_past_success {
                    return bad("a timeout is no success".into());
                }
                if let (true, Some(rule)) = (ep.success, &rules.success) {
                    let (from, tol) = (motion.obs(i, t), motion.tolerance(i, t, &reached));
                    if !rule.may_succeed(from, &reached, tol) {
                        return bad(format!(
                            "flagged a success {} from the goal, beyond the success radius {} \
                             (the position the step reached, p + Δp, is {})",
                            rule.distance(from, &reached),
                            rule.radius,
                            saver_core::clip_text(&format!("{reached:?}")),
                        ));
                    }
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
            ends.push(Some(motion.aligned(i, n).to_vec()));
        }
        Ok((
            Ledger {
                next_seq: r.seq.saturating_add(1),
                envs,
                ends,
            },
            verified,
        ))
    }
}

/// A rollout's positions (validated: every array of its shape).
struct Motion<'a> {
    r: &'a Rollout,
    layout: EnvLayout,
}

impl<'a> Motion<'a> {
    fn new(r: &'a Rollout, layout: EnvLayout) -> Self {
        Self { r, layout }
    }

    /// Observation `t` (0..=n) of env `i`.
    fn obs(&self, i: usize, t: usize) -> &'a [f32] {
        let o = self.layout.obs_dim;
        let at = (i * (self.r.n_steps + 1) + t) * o;
        &self.r.obs[at..at + o]
    }

    /// p in observation `t` of env `i`.
    fn aligned(&self, i: usize, t: usize) -> &'a [f32] {
        let l = &self.layout;
        &self.obs(i, t)[l.aligned_start..l.aligned_start + l.aligned_dim]
    }

    /// Where step `t` of env `i` went, p + Δp, into `reached`, checked against the p'
    /// that follows it when the rollout holds it (the next observation, or a timeout's
    /// final one).
    fn step(&self, i: usize, t: usize, done: bool, reached: &mut Vec<f32>) -> Result<()> {
        let (d, s) = (self.layout.aligned_dim, i * self.r.n_steps + t);
        let p = self.aligned(i, t);
        reached.clear();
        reached.extend(
            p.iter()
                .zip(&self.r.state_delta[s * d..(s + 1) * d])
                .map(|(p, dp)| p + dp),
        );
        let next = if !done {
            Some(self.aligned(i, t + 1))
        } else {
            let o = self.layout.obs_dim;
            self.r
                .timeouts
                .binary_search(&(s as u32))
                .ok()
                .and_then(|k| {
                    let a = k * o + self.layout.aligned_start;
                    self.r.timeout_obs.get(a..a + d)
                })
        };
        if let Some(next) = next {
            self.agrees(reached, next, p, || format!("step {t} of env {i}"))?;
        }
        Ok(())
    }

    /// A continuing rollout's env `i` starts where the one before ended (`end`).
    fn starts_at(&self, i: usize, end: &[f32]) -> Result<()> {
        self.agrees(end, self.aligned(i, 0), end, || {
            format!("env {i}'s first observation")
        })
    }

    /// Refuses `got` (a p' reported) that is not `want` (p + Δp) up to rounding; `what`
    /// names the place, only when it is refused.
    fn agrees(
        &self,
        want: &[f32],
        got: &[f32],
        p: &[f32],
        what: impl FnOnce() -> String,
    ) -> Result<()> {
        let off = (0..want.len()).find(|&j| {
            let diff = (want[j] - got[j]).abs();
            diff.is_nan() || diff > tolerance(p[j], got[j])
        });
        match off {
            None => Ok(()),
            Some(j) => Err(CoreError::Data(format!(
                "{}: aligned entry {} is {}, but the position before it plus its \
                 state change is {} (each step moves p by exactly its state_delta, and \
                 a rollout starts where the one before ended)",
                what(),
                self.layout.aligned_start + j,
                got[j],
                want[j]
            ))),
        }
    }

    /// The rounding a success check at step `t` of env `i` allows.
    fn tolerance(&self, i: usize, t: usize, reached: &[f32]) -> f32 {
        self.aligned(i, t)
            .iter()
            .zip(reached)
            .map(|(&p, &q)| tolerance(p, q))
            .fold(0.0, f32::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use saver_core::rollout::Episode;

    /// Rules of a one-entry observation that is p, with the step limit 1000.
    fn rules(success: Option<SuccessRule>) -> EpisodeRules {
        EpisodeRules {
            max_len: 1000,
            layout: EnvLayout {
                obs_dim: 1,
                continuous: 1,
                choices: 0,
                aligned_start: 0,
                aligned_dim: 1,
            },
            success,
            continue_past_success: false,
        }
    }

    /// Success within 0.1 of the origin.
    const NEAR_ORIGIN: Option<SuccessRule> = Some(SuccessRule {
        radius: 0.1,
        goal_start: None,
    });

    /// One env, `n` steps, reward 0.25 per step (d = 1), done at the given steps; p
    /// stays at 0 (each Δp is 0).
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
            state_delta: vec![0.0; n],
            vector_reward: vec![0.25; n],
            env_reward: vec![],
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
        let (l, v) = l.check(&rollout(0, 4, &[], &[]), &rules(None)).unwrap();
        assert!(v.is_empty());
        let (l2, v) = l
            .check(&rollout(1, 4, &[2], &[(7, true, 1.75)]), &rules(None))
            .unwrap();
        assert_eq!(v, vec![true]);
        // A forged length of 1 (the attack that moved the mean from 990 to 1), a
        // wrong return, a failure before the limit: refused.
        for forged in [(1, true, 1.75), (7, true, 0.25), (7, false, 1.75)] {
            let e = l
                .check(&rollout(1, 4, &[2], &[forged]), &rules(None))
                .unwrap_err();
            assert!(e.to_string().contains("env 0 ending at step 2"), "{e}");
        }
        // After the end the count starts again: rollout 2 ends at step 0 → 1 + 1 = 2.
        let (_, v) = l2
            .check(&rollout(2, 4, &[0], &[(2, true, 0.5)]), &rules(None))
            .unwrap();
        assert_eq!(v, vec![true]);
    }

    #[test]
    fn after_a_gap_an_episode_is_bounded_but_not_counted() {
        // Sequence 5 after 0: the envs ran unseen in between.
        let l = Ledger::fresh(1);
        let (_, v) = l
            .check(&rollout(5, 4, &[2], &[(40, true, 3.0)]), &rules(None))
            .unwrap();
        assert_eq!(v, vec![false]);
        // Still no shorter than its steps in this rollout (3).
        assert!(l
            .check(&rollout(5, 4, &[2], &[(2, true, 0.5)]), &rules(None))
            .is_err());
        // The step limit: a timeout of 1000 steps is no success.
        let mut r = rollout(5, 4, &[3], &[(1000, true, 0.0)]);
        (r.timeouts, r.timeout_obs) = (vec![3], vec![0.0]);
        assert!(l.check(&r, &rules(None)).is_err());
        r.episodes[0].success = false;
        assert!(l.check(&r, &rules(None)).is_ok());
    }

    /// A run that goes on past success: an episode that ends at the step limit inside
    /// the success box (p = 0.05 against the radius 0.1) is a timeout and a success,
    /// but one ending outside it (p = 0.5), or a timeout before the limit, is not.
    #[test]
    fn past_success_a_timeout_inside_the_box_is_a_success() {
        let l = Ledger::fresh(1);
        let on = EpisodeRules {
            continue_past_success: true,
            ..rules(NEAR_ORIGIN)
        };
        let end = |p: f32, length: u32| {
            let mut r = walk(5, p, &[0.0; 4], &[3], &[(length, true, 0.0)]);
            (r.timeouts, r.timeout_obs) = (vec![3], vec![p]);
            r
        };
        assert!(l.check(&end(0.05, 1000), &on).is_ok());
        assert!(l.check(&end(0.05, 1000), &rules(NEAR_ORIGIN)).is_err());
        let outside = l.check(&end(0.5, 1000), &on).unwrap_err().to_string();
        assert!(outside.contains("beyond the success radius"), "{outside}");
        let early = l.check(&end(0.05, 40), &on).unwrap_err().to_string();
        assert!(early.contains("ends at the step limit 1000"), "{early}");
    }

    /// [`rollout`] whose p starts at `start` and moves by `deltas` (the step after a
    /// done flag starts again at `start`).
    fn walk(
        seq: u64,
        start: f32,
        deltas: &[f32],
        done_at: &[usize],
        eps: &[(u32, bool, f32)],
    ) -> Rollout {
        let mut r = rollout(seq, deltas.len(), done_at, eps);
        r.state_delta = deltas.to_vec();
        r.obs = vec![start];
        for (t, dp) in deltas.iter().enumerate() {
            let next = if r.done[t] { start } else { r.obs[t] + dp };
            r.obs.push(next);
        }
        r
    }

    /// The attack of issue 35: episodes of one step flagged as successes far from the
    /// goal. p = 0.9 and Δp = -0.1 reach 0.8, 0.8 from the goal: refused; from 0.15 the
    /// same step reaches 0.05, inside the radius 0.1: a success.
    #[test]
    fn a_success_far_from_the_goal_is_refused() {
        let l = Ledger::fresh(1);
        let forged = walk(0, 0.9, &[-0.1; 4], &[0, 1, 2, 3], &[(1, true, 0.25); 4]);
        let e = l
            .check(&forged, &rules(NEAR_ORIGIN))
            .unwrap_err()
            .to_string();
        assert!(e.contains("beyond the success radius 0.1"), "{e}");
        // Without a rule the learner cannot tell (a custom env whose own `terminated`
        // is the success).
        assert!(l.check(&forged, &rules(None)).is_ok());
        let real = walk(0, 0.15, &[-0.1; 4], &[0, 1, 2, 3], &[(1, true, 0.25); 4]);
        assert!(l.check(&real, &rules(NEAR_ORIGIN)).is_ok());
        // The goal can be observation entries: obs = [g, p], g = 0.85 next to p = 0.9.
        let mut beside = walk(0, 0.9, &[-0.1; 4], &[0, 1, 2, 3], &[(1, true, 0.25); 4]);
        beside.obs = beside.obs.iter().flat_map(|&p| [0.85, p]).collect();
        let mut in_obs = rules(Some(SuccessRule {
            radius: 0.1,
            goal_start: Some(0),
        }));
        in_obs.layout.obs_dim = 2;
        in_obs.layout.aligned_start = 1;
        assert!(l.check(&beside, &in_obs).is_ok());
    }

    /// A step that does not move p by its Δp, a timeout whose final p is not p + Δp,
    /// and a rollout that does not start where the one before ended are refused; after
    /// a gap in the sequence numbers the start is not known.
    #[test]
    fn positions_follow_the_state_changes_within_and_across_rollouts() {
        let l = Ledger::fresh(1);
        let r0 = walk(0, -0.5, &[0.1; 4], &[], &[]);
        let (l1, _) = l.check(&r0, &rules(NEAR_ORIGIN)).unwrap();
        // p went -0.5 → -0.1; the next rollout starts there.
        let next = walk(1, -0.1, &[0.05; 4], &[1], &[(6, true, 1.5)]);
        assert!(l1.check(&next, &rules(NEAR_ORIGIN)).is_ok());
        let jumped = walk(1, 0.3, &[0.05; 4], &[], &[]);
        let e = l1
            .check(&jumped, &rules(NEAR_ORIGIN))
            .unwrap_err()
            .to_string();
        assert!(e.contains("env 0's first observation"), "{e}");
        assert!(l1
            .check(&walk(7, 0.3, &[0.05; 4], &[], &[]), &rules(None))
            .is_ok());
        // Step 2 reports Δp 0.05 but p moves by 0.5 (a teleport toward the goal).
        let mut teleport = walk(0, -0.5, &[0.05; 4], &[], &[]);
        teleport.obs[3] += 0.45;
        teleport.obs[4] += 0.45;
        let e = l.check(&teleport, &rules(None)).unwrap_err().to_string();
        assert!(e.contains("step 2 of env 0"), "{e}");
        // A timeout at step 3 whose final observation is 0.2 away from p + Δp.
        let mut r = walk(5, -0.5, &[0.05; 4], &[3], &[(1000, false, 0.0)]);
        r.timeouts = vec![3];
        r.timeout_obs = vec![-0.3 + 0.2];
        let e = l.check(&r, &rules(None)).unwrap_err().to_string();
        assert!(e.contains("step 3 of env 0"), "{e}");
        r.timeout_obs = vec![-0.3];
        assert!(l.check(&r, &rules(None)).is_ok());
    }
}
