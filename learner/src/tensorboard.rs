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
}
