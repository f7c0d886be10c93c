//! Event frames: `E = Σ p·C` over index ranges, batched, with optional undistortion.
