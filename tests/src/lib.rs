//! Cross-crate tests of GETAvatar. Native tests live in `tests/tests/*.rs`; the browser
//! end-to-end test is `tests/e2e/app.e2e.mjs`, run by `cargo xtask test`.

/// The fuzz targets' bodies (`fuzz/harness.rs`, shared with the cargo-fuzz crate), so
/// `tests/fuzz_regressions.rs` replays the kept corpora and crash inputs on stable.
#[path = "../../fuzz/harness.rs"]
pub mod fuzz_harness;
