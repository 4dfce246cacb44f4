//! Every input the fuzzers keep (`fuzz/corpus/<target>/`: seeds and what libFuzzer found
//! interesting) and every input that once crashed a parser (`fuzz/regressions/<target>/`)
//! goes through the same target body again (`fuzz/harness.rs`), on stable, in CI: none may
//! panic, and none may take long (a fuzz input that allocates or loops is a finding).
//! docs/reliability.md has the runs.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use getavatar_tests::fuzz_harness::TARGETS;

fn files(dir: &Path) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut v: Vec<PathBuf> = rd.map(|e| e.unwrap().path()).filter(|p| p.is_file()).collect();
    v.sort();
    v
}

#[test]
fn every_kept_fuzz_input_parses_without_panicking() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut report = Vec::new();
    for (name, body) in TARGETS {
        let corpus = files(&root.join("corpus").join(name));
        let crashes = files(&root.join("regressions").join(name));
        // Every target has its seeds: a lost corpus directory fails here, not silently.
        assert!(
            corpus.iter().any(|p| p.file_name().unwrap().to_string_lossy().starts_with("seed-")),
            "{name}: no seeds"
        );
        let t0 = Instant::now();
        for path in corpus.iter().chain(&crashes) {
            let bytes = match std::fs::read(path) {
                Ok(b) => b,
                // A fuzzer running in this checkout replaces corpus files as it reduces them.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => panic!("{}: {e}", path.display()),
            };
            let t = Instant::now();
            body(&bytes);
            // Generous for a debug build on 2 cores; libFuzzer's own limit is 10 s.
            assert!(t.elapsed() < Duration::from_secs(20), "{} took {:?}", path.display(), t.elapsed());
        }
        report.push(format!("{name}: {} corpus + {} crash inputs in {:?}", corpus.len(), crashes.len(), t0.elapsed()));
    }
    eprintln!("{}", report.join("\n"));
}

/// The harness covers every corpus directory and every fuzz binary (no target forgotten in
/// one of the three places).
#[test]
fn targets_corpora_and_binaries_agree() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let names: Vec<&str> = TARGETS.iter().map(|(n, _)| *n).collect();
    let mut dirs: Vec<String> = files_and_dirs(&root.join("corpus"))
        .into_iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    dirs.sort();
    let mut bins: Vec<String> = files(&root.join("fuzz_targets"))
        .into_iter()
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    bins.sort();
    let mut sorted: Vec<String> = names.iter().map(|s| s.to_string()).collect();
    sorted.sort();
    assert_eq!(dirs, sorted, "fuzz/corpus directories vs harness targets");
    assert_eq!(bins, sorted, "fuzz/fuzz_targets vs harness targets");
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    for n in &names {
        assert!(manifest.contains(&format!("name = \"{n}\"")), "fuzz/Cargo.toml lacks the bin {n}");
    }
}

fn files_and_dirs(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).filter(|p| p.is_dir()).collect()
}
