//! What a group of runs is called in figures and tables: its algorithm and every
//! setting that sets it apart from the settings the run started from.

use saver_core::config::{Algo, RunConfig};
use saver_core::settings::dotted;

/// Whether setting `key` counts for `algo`: pretraining only for an algorithm with a
/// PCPN.
fn counts(algo: Algo, key: &str) -> bool {
    algo.has_pcpn() || !key.starts_with("pretrain.")
}

/// Each config's series name: its algorithm and, in brackets, the settings it changed
/// ([`variant`]) but those every other config changed too (e.g. `saver repro
/// --pretrain-batches 200` changes every SAVER run alike) or for which that setting
/// does not count. A lone config keeps all its changes.
pub fn series(configs: &[&RunConfig]) -> Vec<String> {
    let changed: Vec<Vec<(String, String)>> = configs.iter().map(|c| variant(c)).collect();
    let shared = |pair: &(String, String)| {
        configs.len() > 1
            && configs
                .iter()
                .zip(&changed)
                .all(|(c, ch)| ch.contains(pair) || !counts(c.algo, &pair.0))
    };
    configs
        .iter()
        .zip(&changed)
        .map(|(c, pairs)| {
            let own: Vec<String> = pairs
                .iter()
                .filter(|p| !shared(p))
                .map(|(k, v)| {
                    if v.is_empty() {
                        k.clone()
                    } else {
                        format!("{k} {v}")
                    }
                })
                .collect();
            if own.is_empty() {
                c.algo.name().to_string()
            } else {
                format!("{} ({})", c.algo.name(), own.join(", "))
            }
        })
        .collect()
}

/// What sets a config apart from its algorithm's default: every setting that differs
/// from the settings the run started from (the paper's for a `--faithful` SAVER run,
/// the default otherwise), as (config.toml name, value), and ("faithful", "") for a
/// faithful run; settings that do not count for its algorithm ([`counts`]) left out.
fn variant(c: &RunConfig) -> Vec<(String, String)> {
    let def = saver_core::algo::recommended(&c.env, c.algo, c.steps);
    let paper = RunConfig::paper(&c.env, c.algo, c.steps);
    let faithful = c.algo == Algo::Saver && c.head == paper.head && c.optimizer == paper.optimizer;
    let base = dotted(if faithful { &paper } else { &def });
    let mut parts: Vec<(String, String)> = dotted(c)
        .into_iter()
        .filter(|(k, _)| !matches!(k.as_str(), "seed" | "steps" | "pcpn_sha256"))
        .filter(|(k, _)| counts(c.algo, k))
        .filter(|(k, v)| base.get(k) != Some(v))
        .collect();
    if faithful {
        parts.push(("faithful".to_string(), String::new()));
    }
    parts
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run's label names every setting it changed, and nothing for the default.
    #[test]
    fn variants_name_every_changed_setting() {
        let env = saver_core::env::EnvSpec::new(saver_core::env::EnvKind::Angle, 4).unwrap();
        let def = saver_core::algo::recommended(&env, Algo::Saver, 100);
        let words = |c: &RunConfig| {
            variant(c)
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        assert_eq!(words(&def), "");
        let mut c = RunConfig {
            seed: 3,
            steps: 7,
            ..def.clone()
        };
        assert_eq!(words(&c), "", "seed and steps are not a variant");
        c.head.log_std_bounds = Some((-1.6, 0.0));
        c.pretrain.batches = 100_000;
        assert_eq!(words(&c), "head.log_std_min -1.6, pretrain.batches 100000");
        let paper = RunConfig::paper(&env, Algo::Saver, 100);
        assert_eq!(words(&paper), "faithful ");
        let slow = RunConfig { lr: 3e-4, ..paper };
        assert_eq!(words(&slow), "lr 0.0003, faithful ");
        // A2C has no PCPN: its pretraining settings are not a variant.
        let mut a2c = saver_core::algo::recommended(&env, Algo::A2c, 100);
        a2c.pretrain.batches = 200;
        assert_eq!(words(&a2c), "");
    }

    /// A change every config shares is not named; one only some have is.
    #[test]
    fn shared_changes_are_left_out_of_the_names() {
        let env = saver_core::env::EnvSpec::new(saver_core::env::EnvKind::Arm, 2).unwrap();
        let a2c = saver_core::algo::recommended(&env, Algo::A2c, 100);
        let mut saver = saver_core::algo::recommended(&env, Algo::Saver, 100);
        saver.pretrain.batches = 200;
        let fast = RunConfig {
            lr: 0.003,
            ..saver.clone()
        };
        assert_eq!(
            series(&[&a2c, &saver, &fast]),
            ["a2c", "saver", "saver (lr 0.003)"]
        );
        assert_eq!(series(&[&saver]), ["saver (pretrain.batches 200)"]);
    }
}
