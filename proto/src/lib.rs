//! saver-proto: what crosses a process boundary. The gRPC protocol generated from
//! `saver.proto` ([`pb`]); weights, checkpoints and PCPNs travel as safetensors bytes
//! (f32, little endian, with a string metadata map), so a client in any language decodes
//! them with the safetensors package alone.

pub mod access;
pub mod admit;
pub mod weights_dir;
pub use access::{endpoint, server, Access, AddToken, CheckToken, ClientAccess};

/// Generated gRPC messages, clients and servers (package `saver.v1`).
#[allow(missing_docs, clippy::all)]
pub mod pb {
    tonic::include_proto!("saver.v1");
}

/// Metadata key with which an actor names its id on StreamRollouts (so that the learner
/// takes it out of the rounds when the stream closes).
pub const ACTOR_ID_KEY: &str = "x-saver-actor-id";
/// Metadata key of the actor's session on StreamRollouts.
pub const SESSION_KEY: &str = "x-saver-session";
/// Metadata key on StreamRollouts: with the value [`ACKS_REFUSALS`] the learner answers
/// only the rollouts it refuses (one message and one wake-up less per rollout for a
/// client that does nothing with an acceptance); without it, every rollout.
pub const ACKS_KEY: &str = "x-saver-acks";
/// Metadata key (in the trailers of an UNAVAILABLE answer) of a learner that is up
/// but waits for its PCPN before it serves: actors keep waiting, with no deadline.
pub const WAITING_KEY: &str = "x-saver-waiting";
/// The value of [`ACKS_KEY`] that asks for refusals only.
pub const ACKS_REFUSALS: &str = "refusals";

/// Largest gRPC message either side accepts (weights of d = 16 nets are ~1 MiB).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

use sha2::{Digest, Sha256};
use std::collections::HashMap;

/// A named f32 tensor in row-major order.
#[derive(Clone, Debug, PartialEq)]
pub struct NamedTensor {
    /// Dotted name, e.g. `agent.l0.w`.
    pub name: String,
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Values, row-major.
    pub data: Vec<f32>,
}

impl NamedTensor {
    /// Number of elements the shape implies.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

/// Errors of the codec.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    /// The bytes are not a valid safetensors file.
    #[error("not a valid safetensors payload: {0}")]
    Safetensors(String),
    /// A tensor is not f32.
    #[error("tensor {name} has dtype {dtype}, expected F32")]
    Dtype {
        /// Tensor name.
        name: String,
        /// Its dtype.
        dtype: String,
    },
    /// A tensor's data length does not match its shape.
    #[error("tensor {name}: {len} values for shape {shape:?}")]
    Shape {
        /// Tensor name.
        name: String,
        /// Number of values.
        len: usize,
        /// Declared shape.
        shape: Vec<usize>,
    },
}

/// Encodes tensors and metadata as safetensors bytes.
pub fn encode(
    tensors: &[NamedTensor],
    metadata: &HashMap<String, String>,
) -> Result<Vec<u8>, CodecError> {
    let mut views = Vec::with_capacity(tensors.len());
    for t in tensors {
        if t.data.len() != t.numel() {
            return Err(CodecError::Shape {
                name: t.name.clone(),
                len: t.data.len(),
                shape: t.shape.clone(),
            });
        }
        let bytes: &[u8] = f32_bytes(&t.data);
        let view =
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, t.shape.clone(), bytes)
                .map_err(|e| CodecError::Safetensors(e.to_string()))?;
        views.push((t.name.clone(), view));
    }
    let meta = if metadata.is_empty() {
        None
    } else {
        Some(metadata.clone())
    };
    safetensors::serialize(views, meta).map_err(|e| CodecError::Safetensors(e.to_string()))
}

/// Decodes safetensors bytes into tensors (sorted by name) and metadata.
///
/// The header is parsed once (`read_metadata` checks every tensor's offsets and size
/// against the buffer) and each tensor is read straight into its own vector: an actor
/// decodes every weights version it acts with, so this runs once per round.
pub fn decode(bytes: &[u8]) -> Result<(Vec<NamedTensor>, HashMap<String, String>), CodecError> {
    let (n, header) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| CodecError::Safetensors(e.to_string()))?;
    // read_metadata found the 8-byte length, the header and every tensor in `bytes`.
    let body = &bytes[8 + n..];
    let mut infos: Vec<(String, &safetensors::tensor::TensorInfo)> =
        header.tensors().into_iter().collect();
    infos.sort_unstable_by(|a, b| a.0.cmp(&b.0));
    let mut out = Vec::with_capacity(infos.len());
    for (name, info) in infos {
        if info.dtype != safetensors::Dtype::F32 {
            return Err(CodecError::Dtype {
                name,
                dtype: format!("{:?}", info.dtype),
            });
        }
        let raw = &body[info.data_offsets.0..info.data_offsets.1];
        out.push(NamedTensor {
            name,
            shape: info.shape.clone(),
            data: f32s_of(raw),
        });
    }
    Ok((out, header.metadata().clone().unwrap_or_default()))
}

/// The little-endian f32 values of `raw` (a multiple of 4 bytes long), in one copy.
fn f32s_of(raw: &[u8]) -> Vec<f32> {
    let n = raw.len() / 4;
    let mut data: Vec<f32> = Vec::with_capacity(n);
    // SAFETY: the vector has room for n values, i.e. n * 4 bytes; every byte pattern is
    // a valid f32 (as in `f32_bytes`, the target is little endian), so all n are set.
    unsafe {
        std::ptr::copy_nonoverlapping(raw.as_ptr(), data.as_mut_ptr().cast::<u8>(), n * 4);
        data.set_len(n);
    }
    data
}

/// Largest safetensors header [`read_metadata`] reads (ours are a few KiB).
const MAX_HEADER: u64 = 16 << 20;

/// The string metadata of a safetensors file, read from its header alone (the
/// tensors are neither read nor decoded).
pub fn read_metadata(mut file: impl std::io::Read) -> Result<HashMap<String, String>, CodecError> {
    let bad = |why: String| CodecError::Safetensors(why);
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|e| bad(format!("reading the header length: {e}")))?;
    let len = u64::from_le_bytes(len);
    if len > MAX_HEADER {
        return Err(bad(format!("a header of {len} bytes is over {MAX_HEADER}")));
    }
    let mut header = vec![0u8; len as usize];
    file.read_exact(&mut header)
        .map_err(|e| bad(format!("reading the header: {e}")))?;
    let h: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| bad(format!("header: {e}")))?;
    let Some(meta) = h.get("__metadata__") else {
        return Ok(HashMap::new());
    };
    meta.as_object()
        .map(|m| {
            m.iter()
                .filter_map(|(k, v)| Some((k.clone(), v.as_str()?.to_string())))
                .collect()
        })
        .ok_or_else(|| bad("__metadata__ is not an object".into()))
}

/// Longest client-supplied text an error message repeats, in characters.
pub const ECHO_CHARS: usize = 64;

/// `text` as an error message may repeat it: its first [`ECHO_CHARS`] characters and
/// "…" when it is longer, so that no client can make a refusal larger than the status
/// it travels in (gRPC metadata is capped at a few KiB).
pub fn clip_text(text: &str) -> String {
    clip_chars(text, ECHO_CHARS)
}

/// Longest status message a server sends, in characters (a backstop behind
/// [`clip_text`]: gRPC carries the message in metadata, capped at a few KiB).
pub const MAX_STATUS_CHARS: usize = 1024;

/// The first `n` characters of `text`, and "…" when it is longer.
pub fn clip_chars(text: &str, n: usize) -> String {
    match text.char_indices().nth(n) {
        None => text.to_string(),
        Some((cut, _)) => format!("{}…", &text[..cut]),
    }
}

/// Lower-case hex sha256 of bytes.
pub fn sha256_hex(bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

fn f32_bytes(data: &[f32]) -> &[u8] {
    // Safetensors is little endian; so is every target we build for.
    #[cfg(target_endian = "big")]
    compile_error!("saver-proto assumes a little-endian target");
    // SAFETY: f32 has no padding and any byte pattern is a valid u8.
    unsafe { std::slice::from_raw_parts(data.as_ptr().cast::<u8>(), std::mem::size_of_val(data)) }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 64 characters pass whole; 65 (or 1 MiB) are cut to 64 and "…"; a cut never
    /// splits a character (ü is 2 bytes).
    #[test]
    fn echoed_text_is_cut_at_64_characters() {
        let exact = "a".repeat(64);
        assert_eq!(clip_text(&exact), exact);
        assert_eq!(clip_text(&"a".repeat(65)), format!("{exact}…"));
        let huge = "ü".repeat(1 << 20);
        let cut = clip_text(&huge);
        assert_eq!(cut.chars().count(), 65);
        assert!(cut.starts_with("üü") && cut.ends_with('…'));
    }

    #[test]
    fn round_trip_keeps_values_shapes_and_metadata() {
        let t = vec![
            NamedTensor {
                name: "b".into(),
                shape: vec![2, 2],
                data: vec![1.0, -2.5, f32::MIN_POSITIVE, 3.0e7],
            },
            NamedTensor {
                name: "a".into(),
                shape: vec![1],
                data: vec![0.125],
            },
        ];
        let meta = HashMap::from([("version".to_string(), "7".to_string())]);
        let bytes = encode(&t, &meta).unwrap();
        let (back, m) = decode(&bytes).unwrap();
        assert_eq!(m["version"], "7");
        assert_eq!(back.len(), 2);
        assert_eq!(back[0], t[1]);
        assert_eq!(back[1], t[0]);
    }

    #[test]
    fn garbage_and_mismatched_shapes_are_errors() {
        assert!(decode(b"not safetensors at all").is_err());
        assert!(decode(&[255; 8]).is_err());
        let bad = NamedTensor {
            name: "x".into(),
            shape: vec![3],
            data: vec![1.0],
        };
        assert!(matches!(
            encode(&[bad], &HashMap::new()),
            Err(CodecError::Shape { .. })
        ));
    }

    #[test]
    fn decode_refuses_cut_or_padded_bytes_and_other_dtypes() {
        let t = NamedTensor {
            name: "w".into(),
            shape: vec![2, 3],
            data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        };
        let bytes = encode(std::slice::from_ref(&t), &HashMap::new()).unwrap();
        assert_eq!(decode(&bytes).unwrap().0, vec![t]);
        // One byte short of the last value, or one byte past it.
        assert!(decode(&bytes[..bytes.len() - 1]).is_err());
        let mut long = bytes.clone();
        long.push(0);
        assert!(decode(&long).is_err());
        // Three f64 values (24 bytes): a well-formed file of another dtype.
        let view =
            safetensors::tensor::TensorView::new(safetensors::Dtype::F64, vec![3], &[0u8; 24])
                .unwrap();
        let f64s = safetensors::serialize([("d", view)], None).unwrap();
        match decode(&f64s) {
            Err(CodecError::Dtype { name, dtype }) => {
                assert_eq!((name.as_str(), dtype.as_str()), ("d", "F64"))
            }
            other => panic!("an f64 tensor decoded: {other:?}"),
        }
    }

    #[test]
    fn metadata_reads_from_the_header_alone() {
        let t = NamedTensor {
            name: "w".into(),
            shape: vec![3],
            data: vec![1.0, 2.0, 3.0],
        };
        let meta = HashMap::from([("config".to_string(), "{}".to_string())]);
        let bytes = encode(&[t], &meta).unwrap();
        assert_eq!(read_metadata(&bytes[..]).unwrap(), meta);
        // The header is all it needs: cut the tensor data off.
        let header_end = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        assert_eq!(read_metadata(&bytes[..header_end]).unwrap(), meta);
        assert!(read_metadata(&bytes[..header_end - 1]).is_err());
        assert!(read_metadata(&[255u8; 8][..]).is_err());
    }

    #[test]
    fn sha256_of_abc() {
        // FIPS 180-2 test vector.
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }
}
