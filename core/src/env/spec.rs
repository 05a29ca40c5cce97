//! Environments as data: an [`EnvSpec`] is a name, a dimension d, a layout
//! ([`EnvLayout`]) and the values the env can produce ([`EnvBounds`], both in
//! layout.rs). The paper's
//! angle, select and arm are presets of it ([`EnvKind`]); a user's env is a spec of its
//! own ([`EnvSpec::custom`]) whose actors bring the env itself.

use super::layout::{EnvBounds, EnvLayout};
use super::preset::{EnvKind, Routing};
use super::{Env, SuccessRule, SUCCESS_RADIUS};
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Largest d, observation or action size of an env spec.
pub const MAX_ENV_DIM: usize = 1024;

/// An environment: the identity of the dynamics a PCPN models and what actors and the
/// learner need to know of it. Valid by construction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "EnvRepr", into = "EnvRepr")]
pub struct EnvSpec {
    /// The preset, if it is one.
    preset: Option<EnvKind>,
    /// The name (a preset's, or a user's).
    name: String,
    /// Layout.
    layout: EnvLayout,
    /// Bounds.
    bounds: EnvBounds,
    /// A custom env's declared success rule (presets have theirs by kind).
    success: Option<SuccessRule>,
}

impl fmt::Display for EnvSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-d{}", self.name, self.dim())
    }
}

impl EnvSpec {
    /// The preset `kind` at dimension `dim` (validated for the kind).
    pub fn new(kind: EnvKind, dim: usize) -> Result<Self> {
        if let Some(why) = (kind.preset().bad_dim)(dim) {
            return Err(CoreError::Config(format!("dim: {why}")));
        }
        if dim > MAX_ENV_DIM {
            return Err(CoreError::Config(format!(
                "dim: {dim} is larger than the supported {MAX_ENV_DIM}"
            )));
        }
        Ok(Self {
            preset: Some(kind),
            name: kind.name().to_string(),
            layout: kind.layout(dim),
            bounds: kind.bounds(dim),
            success: None,
        })
    }

    /// The smallest custom environment: obs [x, y] in [−1, 1]², one continuous action,
    /// x the aligned entry, moving by at most `max_change` a step (what `--help`
    /// resolves a custom env's defaults on, and the tests' stand-in for one).
    pub fn unit_custom(name: &str, max_change: f32) -> Result<Self> {
        let layout = EnvLayout {
            obs_dim: 2,
            continuous: 1,
            choices: 0,
            aligned_start: 0,
            aligned_dim: 1,
        };
        let bounds = EnvBounds {
            obs_low: vec![-1.0; 2],
            obs_high: vec![1.0; 2],
            max_change,
        };
        Self::custom(name, layout, bounds)
    }

    /// A user's environment: `name` (letters, digits, `_`, `.`, `-`; not a preset's),
    /// its layout and bounds, all checked.
    pub fn custom(name: &str, layout: EnvLayout, bounds: EnvBounds) -> Result<Self> {
        let shown = crate::clip_text(name);
        let bad = |why: String| Err(CoreError::Config(format!("env {shown:?}: {why}")));
        let name_ok = !name.is_empty()
            && name.len() <= 64
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '-'));
        if !name_ok {
            return bad("a name is 1-64 letters, digits, '_', '.' or '-'".into());
        }
        if EnvKind::parse(name).is_ok() {
            return bad("is a preset's name; a custom env needs its own".into());
        }
        let l = &layout;
        for (what, v) in [
            ("obs_dim", l.obs_dim),
            ("aligned_dim", l.aligned_dim),
            ("action dims", l.action_dim()),
        ] {
            if !(1..=MAX_ENV_DIM).contains(&v) {
                return bad(format!("{what} {v} is not in 1..={MAX_ENV_DIM}"));
            }
        }
        if l.aligned_start + l.aligned_dim > l.obs_dim {
            return bad(format!(
                "the aligned entries {}..{} are not inside the {} observation entries",
                l.aligned_start,
                l.aligned_start + l.aligned_dim,
                l.obs_dim
            ));
        }
        let b = &bounds;
        if b.obs_low.len() != l.obs_dim || b.obs_high.len() != l.obs_dim {
            return bad(format!(
                "bounds have {} and {} entries for {} observation entries",
                b.obs_low.len(),
                b.obs_high.len(),
                l.obs_dim
            ));
        }
        let finite_interval = |lo: f32, hi: f32| lo.is_finite() && hi.is_finite() && lo <= hi;
        if let Some(i) = (0..l.obs_dim).find(|&i| !finite_interval(b.obs_low[i], b.obs_high[i])) {
            return bad(format!(
                "observation entry {i}: [{}, {}] is not a finite interval",
                b.obs_low[i], b.obs_high[i]
            ));
        }
        if !(b.max_change.is_finite() && b.max_change > 0.0) {
            return bad(format!(
                "max_change {} must be finite and > 0",
                b.max_change
            ));
        }
        Ok(Self {
            preset: None,
            name: name.to_string(),
            layout,
            bounds,
            success: None,
        })
    }

    /// This custom env with its success rule declared (`None`: its own `terminated`
    /// is the success, which the learner cannot check). A preset's rule is its kind's.
    pub fn with_success(mut self, rule: Option<SuccessRule>) -> Result<Self> {
        let Some(r) = rule else {
            self.success = None;
            return Ok(self);
        };
        let bad = |why: String| Err(CoreError::Config(format!("env {self}: success: {why}")));
        if self.preset.is_some() {
            return bad("a preset's success rule is its kind's; it declares none".into());
        }
        if !(r.radius.is_finite() && r.radius > 0.0) {
            return bad(format!("radius {} must be finite and > 0", r.radius));
        }
        if let Some(g) = r.goal_start {
            if g.saturating_add(self.dim()) > self.layout.obs_dim {
                return bad(format!(
                    "the goal entries {g}..{} are not inside the {} observation entries",
                    g.saturating_add(self.dim()),
                    self.layout.obs_dim
                ));
            }
        }
        self.success = Some(r);
        Ok(self)
    }

    /// When an episode succeeds, if the learner can tell: a preset's rule (goal at the
    /// origin, or the arm's goal in observation entries 0..2; radius
    /// [`SUCCESS_RADIUS`]), or what a custom env declared.
    pub fn success_rule(&self) -> Option<SuccessRule> {
        match self.preset {
            Some(kind) => Some(SuccessRule {
                radius: SUCCESS_RADIUS,
                goal_start: kind.preset().goal_start,
            }),
            None => self.success,
        }
    }

    /// The success rule a custom env declared (`None` for a preset, whose rule is its
    /// kind's, and for a custom env without one): what the wire carries.
    pub fn declared_success(&self) -> Option<SuccessRule> {
        self.success
    }

    /// What a PCPN models of this env: the spec without its success rule (a PCPN of
    /// a custom env serves it whatever its episodes count as success).
    pub fn dynamics(&self) -> Self {
        Self {
            success: None,
            ..self.clone()
        }
    }

    /// The preset it is, if it is one.
    pub fn kind(&self) -> Option<EnvKind> {
        self.preset
    }

    /// Which parts of an action move which coordinate ([`Routing`]); a custom env
    /// declares none, so it is [`Routing::Shared`].
    pub fn routing(&self) -> Routing {
        self.preset.map_or(Routing::Shared, |k| k.preset().routing)
    }

    /// Whether continuous action dim j moves state-aligned coordinate j alone (point
    /// and the bandit), so that coordinate j's advantage can weigh action dim j (QRRL's
    /// vector variant).
    pub fn actions_aligned(&self) -> bool {
        self.routing() == Routing::Own
    }

    /// The name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// d: the state-aligned entries (and vector reward components).
    pub fn dim(&self) -> usize {
        self.layout.aligned_dim
    }

    /// The data layout.
    pub fn layout(&self) -> EnvLayout {
        self.layout
    }

    /// What its observations and steps can hold (the learner refuses rollouts
    /// outside it).
    pub fn bounds(&self) -> EnvBounds {
        self.bounds.clone()
    }

    /// A fresh instance of a preset with the default goal; a custom env's actors bring
    /// their own.
    pub fn make(&self, max_steps: u32) -> Result<Box<dyn Env>> {
        match self.preset {
            Some(kind) => Ok((kind.preset().make)(self.dim(), max_steps)),
            None => Err(CoreError::Config(format!(
                "{self} is a custom env, which this build cannot step: serve the run with \
                 `saver learner --config FILE` and let the env's own actors act for it (Python: \
                 `saver-actor act`, docs/GUIDE.md \"Bring your own environment\")"
            ))),
        }
    }
}

/// The written form of [`EnvSpec`]: a preset as `kind` and `dim`; a custom env as
/// `name`, `layout` and `bounds`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct EnvRepr {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    kind: Option<EnvKind>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    name: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    dim: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    layout: Option<EnvLayout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    bounds: Option<EnvBounds>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    success: Option<SuccessRule>,
}

impl TryFrom<EnvRepr> for EnvSpec {
    type Error = CoreError;
    fn try_from(r: EnvRepr) -> Result<Self> {
        match (r.kind, r.name, r.layout, r.bounds) {
            (Some(kind), None, None, None) if r.success.is_none() => {
                let dim = r
                    .dim
                    .ok_or_else(|| CoreError::Config("env.dim is missing".into()))?;
                Self::new(kind, dim)
            }
            (None, Some(name), Some(layout), Some(bounds)) => {
                let spec = Self::custom(&name, layout, bounds)?.with_success(r.success)?;
                match r.dim {
                    Some(d) if d != spec.dim() => Err(CoreError::Config(format!(
                        "env.dim {d} is not the layout's aligned_dim {}",
                        spec.dim()
                    ))),
                    _ => Ok(spec),
                }
            }
            _ => Err(CoreError::Config(
                "env: a preset (kind and dim) or a custom env (name, layout and bounds, \
                 optionally success)"
                    .into(),
            )),
        }
    }
}

impl From<EnvSpec> for EnvRepr {
    fn from(s: EnvSpec) -> Self {
        let dim = Some(s.dim());
        match s.preset {
            Some(kind) => Self {
                kind: Some(kind),
                name: None,
                dim,
                layout: None,
                bounds: None,
                success: None,
            },
            None => Self {
                kind: None,
                name: Some(s.name),
                dim,
                layout: Some(s.layout),
                bounds: Some(s.bounds),
                success: s.success,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A goal-reaching env of a user's: 4 observation entries, the last two the
    /// position, one continuous action per position entry.
    fn reacher() -> EnvSpec {
        let layout = EnvLayout {
            obs_dim: 4,
            continuous: 2,
            choices: 0,
            aligned_start: 2,
            aligned_dim: 2,
        };
        let bounds = EnvBounds {
            obs_low: vec![-1.0, -1.0, -0.3, -0.3],
            obs_high: vec![1.0, 1.0, 0.3, 0.3],
            max_change: 0.05,
        };
        EnvSpec::custom("reacher", layout, bounds).unwrap()
    }

    #[test]
    fn presets_and_custom_envs_read_back_and_presets_keep_their_short_form() {
        let angle = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        assert_eq!(
            serde_json::to_string(&angle).unwrap(),
            r#"{"kind":"angle","dim":4}"#
        );
        let r = reacher();
        assert_eq!(r.to_string(), "reacher-d2");
        assert_eq!(r.kind(), None);
        for s in [angle, r] {
            let json: EnvSpec = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
            assert_eq!(json, s);
            let toml_text = toml::to_string(&s).unwrap();
            assert_eq!(toml::from_str::<EnvSpec>(&toml_text).unwrap(), s);
        }
        assert!(reacher()
            .make(10)
            .err()
            .unwrap()
            .to_string()
            .contains("let the env's own actors act for it"));
    }

    #[test]
    fn bad_custom_envs_are_refused_by_what_is_wrong() {
        let r = reacher();
        let (l, b) = (r.layout(), r.bounds());
        let cases: Vec<(EnvLayout, EnvBounds, &str, &str)> = vec![
            (l, b.clone(), "angle", "preset"),
            (l, b.clone(), "re acher", "letters"),
            (
                EnvLayout {
                    aligned_start: 3,
                    ..l
                },
                b.clone(),
                "r",
                "inside",
            ),
            (
                l,
                EnvBounds {
                    obs_low: vec![0.0; 3],
                    ..b.clone()
                },
                "r",
                "entries",
            ),
            (
                l,
                EnvBounds {
                    obs_high: vec![1.0, 1.0, f32::INFINITY, 0.3],
                    ..b.clone()
                },
                "r",
                "entry 2",
            ),
            (
                l,
                EnvBounds {
                    max_change: 0.0,
                    ..b.clone()
                },
                "r",
                "max_change",
            ),
            (EnvLayout { obs_dim: 0, ..l }, b.clone(), "r", "obs_dim"),
        ];
        for (layout, bounds, name, want) in cases {
            let e = EnvSpec::custom(name, layout, bounds)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{want}: {e}");
        }
    }

    /// A custom env's success rule reads back from TOML and JSON, is checked, and
    /// leaves what a PCPN models alone; presets have theirs by kind.
    #[test]
    fn success_rules_are_declared_checked_and_not_part_of_the_dynamics() {
        let rule = SuccessRule {
            radius: 0.05,
            goal_start: Some(0),
        };
        let r = reacher().with_success(Some(rule)).unwrap();
        assert_eq!(r.success_rule(), Some(rule));
        let toml_text = toml::to_string(&r).unwrap();
        assert!(toml_text.contains("[success]"), "{toml_text}");
        assert_eq!(toml::from_str::<EnvSpec>(&toml_text).unwrap(), r);
        assert_ne!(r, reacher());
        assert_eq!(r.dynamics(), reacher());
        // Goal entries 3..5 are past the 4 observation entries; radius 0; a preset.
        for (rule, want) in [
            (
                SuccessRule {
                    radius: 0.05,
                    goal_start: Some(3),
                },
                "3..5",
            ),
            (
                SuccessRule {
                    radius: 0.0,
                    goal_start: None,
                },
                "radius 0",
            ),
        ] {
            let e = reacher().with_success(Some(rule)).unwrap_err().to_string();
            assert!(e.contains(want), "{want}: {e}");
        }
        let arm = EnvSpec::new(EnvKind::Arm, 2).unwrap();
        assert!(arm.clone().with_success(Some(rule)).is_err());
        assert_eq!(
            arm.success_rule(),
            Some(SuccessRule {
                radius: 0.1,
                goal_start: Some(0)
            })
        );
        let angle = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        assert_eq!(angle.success_rule().unwrap().goal_start, None);
        assert_eq!(reacher().success_rule(), None);
    }
}
