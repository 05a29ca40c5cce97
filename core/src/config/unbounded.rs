//! `Option<f64>` settings written as plain numbers, so that config.toml lists every
//! setting: no bound is `inf` (or `-inf`), no Huber κ is 0.

/// `Option<f64>` written as a number where `None` is `inf` (TOML `inf`, JSON `null`).
pub mod inf_is_none {
    use serde::{Deserialize, Deserializer, Serializer};

    /// `None` → inf.
    pub fn serialize<S: Serializer>(v: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(v.unwrap_or(f64::INFINITY))
    }

    /// inf, -inf or null → `None`.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.filter(|v| v.is_finite() || v.is_nan()))
    }
}

/// `Option<f64>` written as a number where `None` is `-inf` (a lower bound).
pub mod neg_inf_is_none {
    use serde::{Deserializer, Serializer};

    /// `None` → -inf.
    pub fn serialize<S: Serializer>(v: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(v.unwrap_or(f64::NEG_INFINITY))
    }

    /// inf, -inf or null → `None`.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        super::inf_is_none::deserialize(d)
    }
}

/// `Option<f64>` written as a number where `None` is 0.
pub mod zero_is_none {
    use serde::{Deserialize, Deserializer, Serializer};

    /// `None` → 0.
    pub fn serialize<S: Serializer>(v: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(v.unwrap_or(0.0))
    }

    /// 0 or null → `None`.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.filter(|&v| v != 0.0))
    }
}
