//! dray-config: the one cluster config (TOML) with validation.
//!
//! The cluster config arrives with the message bus issue; the preprocessing
//! parameters live with the preprocessor in `dray-scene`.
