//! The paper's §3.1 window sampler: random end index and window length, seeded.
