//! Cross-crate tests of GETAvatar. Native tests live in `tests/tests/*.rs`; the browser
//! end-to-end test is `tests/e2e/app.e2e.mjs`, run by `cargo xtask test`.
