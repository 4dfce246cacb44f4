//! Idempotent installation of what building and testing need, and the choice of wasm
//! toolchain: rustup's `wasm32-unknown-unknown` target where it is installed or installable,
//! otherwise Debian's `rustc-web` with `-Zbuild-std` (for machines where rustup cannot
//! download the wasm std). `GETAVATAR_WASM_TOOLCHAIN=rustup|debian` forces one.

use std::path::Path;
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use crate::run;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WasmToolchain {
    Rustup,
    Debian,
}

const DEBIAN_WASM_PACKAGES: [&str; 4] = ["rustc-web", "cargo-web", "rust-web-src", "lld-22"];

fn quiet(cmd: &mut Command) -> Option<String> {
    let out = cmd.stderr(Stdio::null()).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

fn rustup_has_wasm() -> bool {
    quiet(Command::new("rustup").args(["target", "list", "--installed"]))
        .is_some_and(|s| s.lines().any(|l| l.trim() == "wasm32-unknown-unknown"))
}

fn debian_wasm_ready() -> bool {
    Path::new("/usr/bin/rustc").exists()
        && Path::new("/usr/bin/cargo").exists()
        && Path::new("/usr/lib/rustlib/src/rust/library/std").exists()
        && DEBIAN_WASM_PACKAGES.iter().all(|p| dpkg_installed(p))
}

fn dpkg_installed(pkg: &str) -> bool {
    quiet(Command::new("dpkg-query").args(["-W", "-f=${Status}", pkg]))
        .is_some_and(|s| s.contains("install ok installed"))
}

/// Install Debian packages that are missing (apt-get; via sudo when not root).
pub fn apt_install(pkgs: &[&str]) -> Result<()> {
    let missing: Vec<&str> = pkgs.iter().copied().filter(|p| !dpkg_installed(p)).collect();
    if missing.is_empty() {
        return Ok(());
    }
    if !Path::new("/usr/bin/apt-get").exists() {
        bail!("missing packages {missing:?} and no apt-get on this machine: install them by hand");
    }
    let root = quiet(Command::new("id").arg("-u")).is_some_and(|s| s.trim() == "0");
    let sudo = |args: &[&str]| {
        let mut c = if root { Command::new(args[0]) } else { Command::new("sudo") };
        if root {
            c.args(&args[1..]);
        } else {
            c.args(args);
        }
        c.env("DEBIAN_FRONTEND", "noninteractive");
        c
    };
    eprintln!("xtask: installing {missing:?} with apt-get");
    run(&mut sudo(&["apt-get", "update", "-qq"]))?;
    let mut args = vec!["apt-get", "install", "-y", "-qq", "--no-install-recommends"];
    args.extend(&missing);
    run(&mut sudo(&args))
}

/// Decide (and if needed install) the wasm32 toolchain.
pub fn wasm_toolchain() -> Result<WasmToolchain> {
    match std::env::var("GETAVATAR_WASM_TOOLCHAIN").ok().as_deref() {
        Some("rustup") => return Ok(WasmToolchain::Rustup),
        Some("debian") => {
            apt_install(&DEBIAN_WASM_PACKAGES)?;
            return Ok(WasmToolchain::Debian);
        }
        _ => {}
    }
    if rustup_has_wasm() {
        return Ok(WasmToolchain::Rustup);
    }
    if debian_wasm_ready() {
        return Ok(WasmToolchain::Debian);
    }
    eprintln!("xtask: wasm32 target not installed; trying `rustup target add wasm32-unknown-unknown`");
    if Command::new("rustup").args(["target", "add", "wasm32-unknown-unknown"]).status().is_ok_and(|s| s.success())
        && rustup_has_wasm()
    {
        return Ok(WasmToolchain::Rustup);
    }
    eprintln!("xtask: rustup cannot provide the wasm32 std; using Debian's rustc-web with -Zbuild-std");
    apt_install(&DEBIAN_WASM_PACKAGES).context("installing the Debian wasm toolchain")?;
    Ok(WasmToolchain::Debian)
}

/// Path of the Chromium used by the browser tests.
pub fn chromium() -> Result<String> {
    if let Ok(p) = std::env::var("GETAVATAR_CHROMIUM") {
        return Ok(p);
    }
    if !Path::new("/usr/bin/chromium").exists() {
        apt_install(&["chromium"])?;
    }
    Ok("/usr/bin/chromium".into())
}

/// A Vulkan driver for the native wgpu tests: Mesa's lavapipe (software) where none exists;
/// ffmpeg for `trainer motion-from-video` and its test.
pub fn native_test_deps() -> Result<()> {
    if Path::new("/usr/bin/apt-get").exists() {
        apt_install(&["mesa-vulkan-drivers", "ffmpeg"])?;
    }
    Ok(())
}

/// Chromium plus the Node packages of `tests/e2e` (npm ci from the committed lock file).
pub fn browser_test_deps() -> Result<()> {
    chromium()?;
    npm_ci(&crate::root().join("tests/e2e"))
}

/// The app's browser-side packages (`www/`, e.g. MediaPipe Pose), installed from the lock file.
pub fn web_deps() -> Result<()> {
    npm_ci(&crate::root().join("www"))
}

/// Node and npm (apt where missing), then `npm ci` in `dir` unless its node_modules is
/// newer than its lock file.
fn npm_ci(dir: &Path) -> Result<()> {
    if quiet(Command::new("npm").arg("--version")).is_none() {
        apt_install(&["nodejs", "npm"])?;
    }
    let stamp = dir.join("node_modules/.package-lock.json");
    let lock = dir.join("package-lock.json");
    let fresh = match (
        std::fs::metadata(&stamp).and_then(|m| m.modified()),
        std::fs::metadata(&lock).and_then(|m| m.modified()),
    ) {
        (Ok(s), Ok(l)) => s >= l,
        _ => false,
    };
    if !fresh {
        run(Command::new("npm").current_dir(dir).args(["ci", "--no-audit", "--no-fund"]))?;
    }
    Ok(())
}

/// `cargo xtask setup`: everything, up front.
pub fn setup(verbose: bool) -> Result<()> {
    let tc = wasm_toolchain()?;
    browser_test_deps()?;
    native_test_deps()?;
    web_deps()?;
    if verbose {
        println!("wasm toolchain: {tc:?}; chromium: {}; node packages: tests/e2e/node_modules", chromium()?);
    }
    Ok(())
}
