//! Small shared services.
//!
//! - [`rng`]: seeded randomness, identical on every platform
//! - [`profile`]: stage timings of a generation (host, GPU wait, yield)
//! - [`cooperative`]: yielding long work to the browser's event loop

pub mod cooperative;
pub mod profile;
pub mod rng;
