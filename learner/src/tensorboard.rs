//! TensorBoard event files, written by hand (the format is small): a TFRecord file of
//! `Event` protocol buffers, each record `u64 length | u32 masked crc32c(length) | data |
//! u32 masked crc32c(data)`, the first event the file version, then one event per
//! update with the update's scalars as `Summary` values. TensorBoard (and anything that
//! reads its files) lists a run folder's scalars from it.

use crate::metrics::MetricsRow;
use saver_core::rollout::Episode;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// CRC-32C (Castagnoli, reflected polynomial 0x82F63B78), as TFRecord uses.
pub fn crc32c(data: &[u8]) -> u32 {
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    (c >> 1) ^ 0x82F6_3B78
                } else {
                    c >> 1
                };
            }
            *e = c;
        }
        t
    });
    !data.iter().fold(!0u32, |c, &b| {
        table[((c ^ b as u32) & 0xff) as usize] ^ (c >> 8)
    })
}

/// The masked CRC of TFRecord.
fn masked(crc: u32) -> u32 {
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// A length-delimited field.
fn bytes_field(out: &mut Vec<u8>, field: u32, data: &[u8]) {
    varint(out, ((field << 3) | 2) as u64);
    varint(out, data.len() as u64);
    out.extend_from_slice(data);
}

/// An `Event` (tensorflow/core/util/event.proto): wall_time = 1 (double), step = 2
/// (int64), file_version = 3 (string) or summary = 5 (Summary: repeated Value = 1,
/// Value: tag = 1 (string), simple_value = 2 (float)).
fn event(
    wall_time: f64,
    step: i64,
    file_version: Option<&str>,
    scalars: &[(&str, f32)],
) -> Vec<u8> {
    let mut e = Vec::new();
    e.push(0x09);
    e.extend_from_slice(&wall_time.to_le_bytes());
    e.push(0x10);
    varint(&mut e, step as u64);
    if let Some(v) = file_version {
        bytes_field(&mut e, 3, v.as_bytes());
    }
    if !scalars.is_empty() {
        let mut summary = Vec::new();
        for (tag, value) in scalars {
            let mut v = Vec::new();
            bytes_field(&mut v, 1, tag.as_bytes());
            v.push(0x15);
            v.extend_from_slice(&value.to_le_bytes());
            bytes_field(&mut summary, 1, &v);
        }
        bytes_field(&mut e, 5, &summary);
    }
    e
}

/// One TFRecord around `data`.
fn record(data: &[u8]) -> Vec<u8> {
    let len = (data.len() as u64).to_le_bytes();
    let mut r = Vec::with_capacity(data.len() + 16);
    r.extend_from_slice(&len);
    r.extend_from_slice(&masked(crc32c(&len)).to_le_bytes());
    r.extend_from_slice(data);
    r.extend_from_slice(&masked(crc32c(data)).to_le_bytes());
    r
}

/// An open event file in a run folder.
pub struct EventWriter {
    out: BufWriter<File>,
    path: PathBuf,
}

impl EventWriter {
    /// A new event file in `dir` (a resumed run adds a file; TensorBoard reads all).
    pub fn create(dir: &Path) -> std::io::Result<Self> {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let path = dir.join(format!(
            "events.out.tfevents.{}.saver.{}",
            now.as_secs(),
            std::process::id()
        ));
        let mut w = Self {
            out: BufWriter::new(File::create(&path)?),
            path,
        };
        w.out.write_all(&record(&event(
            now.as_secs_f64(),
            0,
            Some("brain.Event:2"),
            &[],
        )))?;
        w.out.flush()?;
        Ok(w)
    }

    /// Writes the run's hyperparameters (the hparams plugin's session start) and
    /// flushes.
    pub fn write_hparams(&mut self, hparams: &[(String, HParam)]) -> std::io::Result<()> {
        let wall = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .as_secs_f64();
        self.out.write_all(&record(&hparams_event(wall, hparams)))?;
        self.out.flush()
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes `scalars` at `step` (non-finite values are left out) and flushes.
    pub fn write(&mut self, step: u64, scalars: &[(&str, f32)]) -> std::io::Result<()> {
        let wall = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .as_secs_f64();
        let finite: Vec<(&str, f32)> = scalars
            .iter()
            .copied()
            .filter(|(_, v)| v.is_finite())
            .collect();
        self.out
            .write_all(&record(&event(wall, step as i64, None, &finite)))?;
        self.out.flush()
    }
}

/// A hyperparameter's value as the hparams plugin holds it (google.protobuf.Value).
#[derive(Clone, Debug, PartialEq)]
pub enum HParam {
    /// number_value.
    Number(f64),
    /// string_value.
    Text(String),
    /// bool_value.
    Bool(bool),
}

/// The settings of a run (a config as JSON) as hyperparameters: every number,
/// string and bool, nested tables joined with "." (`saver.quantiles`), arrays left
/// out, a null (an unbounded value: JSON has no infinity) as the string "inf".
pub fn hparams_of(config: &serde_json::Value) -> Vec<(String, HParam)> {
    fn walk(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, HParam)>) {
        use serde_json::Value as J;
        let key = |k: &str| {
            if prefix.is_empty() {
                k.to_string()
            } else {
                format!("{prefix}.{k}")
            }
        };
        match v {
            J::Object(m) => m.iter().for_each(|(k, v)| walk(&key(k), v, out)),
            J::Number(n) => out.push((
                prefix.into(),
                HParam::Number(n.as_f64().unwrap_or(f64::NAN)),
            )),
            J::String(s) => out.push((prefix.into(), HParam::Text(s.clone()))),
            J::Bool(b) => out.push((prefix.into(), HParam::Bool(*b))),
            J::Null => out.push((prefix.into(), HParam::Text("inf".into()))),
            J::Array(_) => {}
        }
    }
    let mut out = Vec::new();
    walk("", config, &mut out);
    out
}

/// The hparams plugin's session start (tensorboard/plugins/hparams): an `Event` whose
/// summary holds one value, tag `_hparams_/session_start_info`, with metadata
/// (field 9) PluginData {plugin_name = "hparams", content = HParamsPluginData {version
/// 0, session_start_info (3) = SessionStartInfo {hparams (1): map<string, Value>,
/// start_time_secs (5)}}}. TensorBoard's HPARAMS tab lists the run by them.
fn hparams_event(wall_time: f64, hparams: &[(String, HParam)]) -> Vec<u8> {
    let mut start = Vec::new();
    for (k, v) in hparams {
        let mut value = Vec::new();
        match v {
            HParam::Number(x) => {
                value.push(0x11);
                value.extend_from_slice(&x.to_le_bytes());
            }
            HParam::Text(s) => bytes_field(&mut value, 3, s.as_bytes()),
            HParam::Bool(b) => value.extend_from_slice(&[0x20, *b as u8]),
        }
        let mut entry = Vec::new();
        bytes_field(&mut entry, 1, k.as_bytes());
        bytes_field(&mut entry, 2, &value);
        bytes_field(&mut start, 1, &entry);
    }
    start.push(0x29);
    start.extend_from_slice(&wall_time.to_le_bytes());
    let mut content = vec![0x08, 0x00];
    bytes_field(&mut content, 3, &start);
    let mut plugin = Vec::new();
    bytes_field(&mut plugin, 1, b"hparams");
    bytes_field(&mut plugin, 2, &content);
    let mut metadata = Vec::new();
    bytes_field(&mut metadata, 1, &plugin);
    let mut value = Vec::new();
    bytes_field(&mut value, 1, b"_hparams_/session_start_info");
    bytes_field(&mut value, 9, &metadata);
    let mut summary = Vec::new();
    bytes_field(&mut summary, 1, &value);
    let mut e = event(wall_time, 0, None, &[]);
    bytes_field(&mut e, 5, &summary);
    e
}

/// The scalars of one update: metrics.csv's columns (algorithm statistics by name) and
/// the mean return and success rate of the episodes the update saw finish.
pub fn scalars(
    row: &MetricsRow,
    stat_names: &[&'static str],
    episodes: &[Episode],
) -> Vec<(&'static str, f32)> {
    let opt = |v: Option<f64>| v.map_or(f32::NAN, |v| v as f32);
    let mut s = vec![
        ("steps_per_s", row.steps_per_s as f32),
        ("mean_ep_len_100", opt(row.mean_ep_len_100)),
        ("mean_ep_len_100_actor0", opt(row.mean_ep_len_100_actor0)),
        ("episodes", row.episodes as f32),
        ("lag_mean", row.lag_mean as f32),
        ("lag_max", row.lag_max as f32),
        ("stale_dropped", row.stale_dropped as f32),
        ("skipped_updates", row.skipped_updates as f32),
    ];
    s.extend(stat_names.iter().copied().zip(row.stats.iter().copied()));
    if !episodes.is_empty() {
        let n = episodes.len() as f32;
        s.push((
            "episode/return_mean",
            episodes.iter().map(|e| e.ret).sum::<f32>() / n,
        ));
        let won = episodes.iter().filter(|e| e.success).count() as f32;
        s.push(("episode/success_rate", won / n));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_and_records_by_the_book() {
        // The CRC-32C check value of "123456789" (RFC 3720, B.4).
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(crc32c(b""), 0);
        // A record of 3 bytes: length 3 as u64 LE, its masked CRC, the data, its CRC.
        let r = record(b"abc");
        assert_eq!(r.len(), 8 + 4 + 3 + 4);
        assert_eq!(&r[..8], &3u64.to_le_bytes());
        assert_eq!(&r[12..15], b"abc");
        let crc = u32::from_le_bytes(r[15..19].try_into().unwrap());
        assert_eq!(crc, masked(crc32c(b"abc")));
        // One scalar event: 0x09 + 8 bytes, 0x10 + varint(300) = [0xac, 0x02], then the
        // summary field (0x2a) holding one value (0x0a) of tag "x" and 0x15 + f32.
        let e = event(1.5, 300, None, &[("x", 2.0)]);
        assert_eq!(e[0], 0x09);
        assert_eq!(&e[9..12], &[0x10, 0xac, 0x02]);
        let mut value = vec![0x0a, 1, b'x', 0x15];
        value.extend_from_slice(&2.0f32.to_le_bytes());
        let mut want = vec![0x2a, value.len() as u8 + 2, 0x0a, value.len() as u8];
        want.extend_from_slice(&value);
        assert_eq!(&e[12..], &want[..]);
    }

    /// Nested settings flatten to dotted keys; arrays are left out and null is "inf".
    #[test]
    fn hparams_flatten_the_config() {
        let v = serde_json::json!({"algo": "saver", "lr": 0.001, "head": {"mu_bound": null},
                                   "faithful": false, "env": {"bounds": {"obs_low": [0.0]}}});
        let h = hparams_of(&v);
        assert_eq!(
            h,
            vec![
                ("algo".to_string(), HParam::Text("saver".into())),
                ("faithful".to_string(), HParam::Bool(false)),
                ("head.mu_bound".to_string(), HParam::Text("inf".into())),
                ("lr".to_string(), HParam::Number(0.001)),
            ]
        );
    }
}
