//! Settings written by earlier versions: what has moved since is moved into place
//! before a config.toml, a `--config` file or a checkpoint's settings are read, so old
//! run folders still resume and old files still load.

use super::RunConfig;
use crate::{CoreError, Result};

/// Settings that moved: (old section, old key, new section, new key).
const MOVED: &[(&str, &str, &str, &str)] = &[
    ("saver", "qrrl_spread", "qrrl", "spread"),
    ("saver", "qrrl_vector", "qrrl", "vector"),
];

/// Moves every [`MOVED`] setting of a TOML table to its place (a value already at the
/// new place wins).
pub fn upgrade_toml(top: &mut toml::Table) {
    for (old_section, old_key, new_section, new_key) in MOVED {
        let Some(toml::Value::Table(old)) = top.get_mut(*old_section) else {
            continue;
        };
        let Some(v) = old.remove(*old_key) else {
            continue;
        };
        let new = top
            .entry(new_section.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if let toml::Value::Table(new) = new {
            new.entry(new_key.to_string()).or_insert(v);
        }
    }
}

/// [`upgrade_toml`] for the JSON form (a checkpoint's settings).
pub fn upgrade_json(top: &mut serde_json::Value) {
    for (old_section, old_key, new_section, new_key) in MOVED {
        let Some(v) = top
            .get_mut(*old_section)
            .and_then(|s| s.as_object_mut())
            .and_then(|s| s.remove(*old_key))
        else {
            continue;
        };
        if let Some(top) = top.as_object_mut() {
            let new = top
                .entry(new_section.to_string())
                .or_insert_with(|| serde_json::Value::Object(Default::default()));
            if let Some(new) = new.as_object_mut() {
                new.entry(new_key.to_string()).or_insert(v);
            }
        }
    }
}

impl RunConfig {
    /// Reads a config.toml, of this version or an earlier one.
    pub fn from_toml(text: &str) -> Result<Self> {
        let mut top: toml::Table =
            toml::from_str(text).map_err(|e| CoreError::Config(e.to_string()))?;
        upgrade_toml(&mut top);
        toml::Value::Table(top)
            .try_into()
            .map_err(|e: toml::de::Error| CoreError::Config(e.to_string()))
    }

    /// Reads the JSON form (a checkpoint's settings), of this version or an earlier one.
    pub fn from_json(text: &str) -> Result<Self> {
        let mut top: serde_json::Value =
            serde_json::from_str(text).map_err(|e| CoreError::Config(e.to_string()))?;
        upgrade_json(&mut top);
        serde_json::from_value(top).map_err(|e| CoreError::Config(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Algo;
    use crate::env::{EnvKind, EnvSpec};

    /// A QRRL run's settings as a version before `[qrrl]` wrote them: spread and vector
    /// under `[saver]` as qrrl_spread and qrrl_vector, and no `head.log_std_init` (the
    /// default −1 it reads as was every earlier run's).
    fn old_form(c: &RunConfig) -> toml::Table {
        let mut top = toml::Table::try_from(c).unwrap();
        let head = top.get_mut("head").unwrap().as_table_mut().unwrap();
        assert!(head.remove("log_std_init").is_some());
        let qrrl = top.remove("qrrl").unwrap();
        let saver = top.get_mut("saver").unwrap().as_table_mut().unwrap();
        saver.insert("qrrl_spread".into(), qrrl["spread"].clone());
        saver.insert("qrrl_vector".into(), qrrl["vector"].clone());
        top
    }

    #[test]
    fn settings_of_an_earlier_version_still_read() {
        let env = EnvSpec::new(EnvKind::Point, 2).unwrap();
        let mut c = crate::algo::recommended(&env, Algo::Qrrl, 1000);
        c.qrrl.spread = 0.5;
        c.qrrl.vector = true;
        crate::algo::validate(&c).unwrap();
        let old = old_form(&c);
        let text = toml::to_string(&old).unwrap();
        assert!(
            text.contains("qrrl_spread = 0.5") && !text.contains("[qrrl]"),
            "{text}"
        );
        // config.toml and a checkpoint's JSON.
        assert_eq!(RunConfig::from_toml(&text).unwrap(), c);
        let json = serde_json::to_string(&old).unwrap();
        assert_eq!(RunConfig::from_json(&json).unwrap(), c);
        // A `--config` file: the same run, flags over it.
        let dir = std::env::temp_dir().join(format!("saver-upgrade-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("config.toml");
        std::fs::write(&file, &text).unwrap();
        let settings = crate::settings::RunSettings {
            config: Some(file),
            ..Default::default()
        };
        assert_eq!(settings.resolve().unwrap(), c);
        std::fs::remove_dir_all(&dir).unwrap();
        // A file with both forms: the new place wins.
        let mut both = old_form(&c);
        both.insert("qrrl".into(), toml::Value::try_from(&c.qrrl).unwrap());
        both["saver"]["qrrl_spread"] = toml::Value::Float(0.25);
        let read = RunConfig::from_toml(&toml::to_string(&both).unwrap()).unwrap();
        assert_eq!(read.qrrl.spread, 0.5);
        // Nothing else moved: a current file reads unchanged, and an unknown key is
        // still refused.
        assert_eq!(RunConfig::from_toml(&c.to_toml()).unwrap(), c);
        let mut unknown = old_form(&c);
        unknown["saver"]
            .as_table_mut()
            .unwrap()
            .insert("qrrl_typo".into(), toml::Value::Boolean(true));
        let err = RunConfig::from_toml(&toml::to_string(&unknown).unwrap()).unwrap_err();
        assert!(err.to_string().contains("qrrl_typo"), "{err}");
    }
}
