//! Named training configs (`trainer train --cfg configs/NAME.toml`): a recipe as a file
//! instead of a chain of commands and hand edits of `run.json`.
//!
//! ```toml
//! [train]                  # `trainer train` flags by their long names (CLI flags win)
//! data = "data/ds64_64"
//! config = "demo"
//! objective = "reconstruction"
//! steps = 1700
//!
//! [[schedule]]             # run.json fields changed once `after_step` steps are done
//! after_step = 625
//! set = { latent_spread = 0.7 }
//! ```
//!
//! The `[train]` table becomes flags placed before the command line's own, so a flag given on
//! the command line overrides the file's. The schedule is written into `run.json` when the run
//! starts; at each of its steps the run checkpoints and continues with the changed settings,
//! exactly as stopping there, editing `run.json` and resuming would (a continued run is
//! bit-identical to an uninterrupted one).

use std::ffi::OsString;
use std::path::Path;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

/// One change of a run's settings: the `run.json` fields in `set` take their values once
/// `after_step` steps are done (nested objects, such as `generator`, merge field by field).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Scheduled {
    pub after_step: u64,
    pub set: serde_json::Map<String, serde_json::Value>,
}

/// The file: `[train]` flags and the `[[schedule]]` of changes.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CfgFile {
    #[serde(default)]
    train: toml::Table,
    #[serde(default)]
    schedule: Vec<Scheduled>,
}

fn read(path: &Path) -> Result<CfgFile> {
    let text = std::fs::read_to_string(path).with_context(|| format!("--cfg: reading {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("--cfg {}", path.display()))
}

/// The schedule of the config at `path`, in step order.
pub fn schedule(path: &Path) -> Result<Vec<Scheduled>> {
    let mut s = read(path)?.schedule;
    if s.iter().any(|e| e.after_step == 0) {
        bail!("--cfg {}: a schedule's after_step is at least 1 (a run's first settings are its flags)", path.display());
    }
    s.sort_by_key(|e| e.after_step);
    Ok(s)
}

/// The run.json fields a schedule may not change: what the run's tensors, data and random
/// streams are made of (the generator's networks, the discriminators, the data, the seed).
/// `generator.tet_res` (the extraction grid) may change.
const FIXED: [&str; 8] =
    ["discriminator", "data", "resolution", "seed", "objective", "codes_wplus", "batch", "schedule"];

/// `run` (a run.json value) with `set` merged in; an error names a field run.json lacks or
/// one that is fixed.
pub fn apply(
    mut run: serde_json::Value,
    set: &serde_json::Map<String, serde_json::Value>,
) -> Result<serde_json::Value> {
    fn merge(dst: &mut serde_json::Value, src: &serde_json::Map<String, serde_json::Value>, path: &str) -> Result<()> {
        let Some(obj) = dst.as_object_mut() else { bail!("`{path}` is not a table in run.json") };
        for (k, v) in src {
            let here = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
            match (obj.get_mut(k), v) {
                (Some(d @ serde_json::Value::Object(_)), serde_json::Value::Object(v)) => merge(d, v, &here)?,
                (Some(d), v) => *d = v.clone(),
                // Optional fields absent from run.json (skipped when unset) may be set.
                (None, v) if path.is_empty() && OPTIONAL.contains(&k.as_str()) => {
                    obj.insert(k.clone(), v.clone());
                }
                (None, _) => bail!("schedule: run.json has no field `{here}`"),
            }
        }
        Ok(())
    }
    for k in set.keys() {
        if FIXED.contains(&k.as_str()) {
            bail!("schedule: `{k}` is fixed for a run's life");
        }
        if k == "generator" {
            let ok = set[k].as_object().is_some_and(|g| g.keys().all(|f| f == "tet_res"));
            if !ok {
                bail!("schedule: of `generator`, only `tet_res` may change (the networks are fixed for a run's life)");
            }
        }
    }
    merge(&mut run, set, "")?;
    Ok(run)
}

/// run.json fields that are left out while unset.
const OPTIONAL: [&str; 2] = ["latent_spread_geo", "train_only"];

/// `argv` with a `train … --cfg FILE` expanded: the file's `[train]` flags inserted right
/// after `train` (so the command line's own flags, which come later, win). `known` holds the
/// train command's long flag names; a key that is none of them is an error naming the file.
pub fn expand(argv: Vec<OsString>, known: &[String]) -> Result<Vec<OsString>> {
    // The subcommand is the first argument (the CLI has no global flags before it).
    let train_at = 1;
    if argv.get(train_at).is_none_or(|a| a != "train") {
        return Ok(argv);
    }
    let mut path = None;
    for (i, a) in argv.iter().enumerate().skip(train_at + 1) {
        let a = a.to_string_lossy();
        if a == "--cfg" {
            path = argv.get(i + 1).map(|p| p.clone().into());
        } else if let Some(p) = a.strip_prefix("--cfg=") {
            path = Some(p.into());
        }
    }
    let Some(path) = path else { return Ok(argv) };
    let path: std::path::PathBuf = path;
    let file = read(&path)?;
    let mut flags: Vec<OsString> = Vec::new();
    for (k, v) in &file.train {
        let name = k.replace('_', "-");
        if !known.contains(&name) || name == "cfg" {
            bail!("--cfg {}: `{k}` is not a flag of `trainer train`", path.display());
        }
        let value = match v {
            toml::Value::Boolean(true) => None,
            toml::Value::Boolean(false) => continue,
            toml::Value::String(s) => Some(s.clone()),
            toml::Value::Integer(i) => Some(i.to_string()),
            toml::Value::Float(f) => Some(f.to_string()),
            _ => bail!("--cfg {}: `{k}` must be a string, number or boolean", path.display()),
        };
        flags.push(format!("--{name}").into());
        flags.extend(value.map(OsString::from));
    }
    let mut out = argv[..=train_at].to_vec();
    out.extend(flags);
    out.extend_from_slice(&argv[train_at + 1..]);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `[train]`'s keys become flags ahead of the command line's own; a key that is no flag
    /// is refused with the file named.
    #[test]
    fn the_files_flags_come_before_the_command_lines_and_bad_keys_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.toml");
        std::fs::write(&p, "[train]\ndata = \"d\"\nsteps = 7\ncodes_wplus = true\nviews = 4\n").unwrap();
        let known: Vec<String> = ["data", "steps", "codes-wplus", "views", "cfg"].map(String::from).to_vec();
        let argv: Vec<OsString> =
            ["trainer", "train", "--cfg", p.to_str().unwrap(), "--steps", "9"].map(OsString::from).to_vec();
        let got: Vec<String> = expand(argv, &known).unwrap().into_iter().map(|a| a.into_string().unwrap()).collect();
        let want = ["trainer", "train", "--codes-wplus", "--data", "d", "--steps", "7", "--views", "4", "--cfg"];
        assert_eq!(&got[..want.len()], want);
        assert_eq!(&got[want.len() + 1..], ["--steps", "9"]);

        // Another command's `--cfg`-like arguments are left alone.
        let other: Vec<OsString> = ["trainer", "sample", "--out", "train", "--cfg", "x"].map(OsString::from).to_vec();
        assert_eq!(expand(other.clone(), &known).unwrap(), other);

        std::fs::write(&p, "[[schedule]]\nafter_step = 0\nset = { lr_g = 0.1 }\n").unwrap();
        let e = schedule(&p).unwrap_err().to_string();
        assert!(e.contains("at least 1"), "{e}");

        std::fs::write(&p, "[train]\nstepz = 7\n").unwrap();
        let argv: Vec<OsString> = ["trainer", "train", "--cfg", p.to_str().unwrap()].map(OsString::from).to_vec();
        let e = expand(argv, &known).unwrap_err().to_string();
        assert!(e.contains("`stepz` is not a flag"), "{e}");
    }

    #[test]
    fn a_schedule_changes_existing_fields_and_refuses_fixed_or_unknown_ones() {
        let run = serde_json::json!({ "lr_g": 0.0005, "generator": { "tet_res": 64, "w_dim": 32 }, "seed": 0 });
        let set = |j: serde_json::Value| j.as_object().unwrap().clone();
        let got =
            apply(run.clone(), &set(serde_json::json!({ "lr_g": 0.00025, "generator": { "tet_res": 96 } }))).unwrap();
        assert_eq!(got, serde_json::json!({ "lr_g": 0.00025, "generator": { "tet_res": 96, "w_dim": 32 }, "seed": 0 }));
        let e = apply(run.clone(), &set(serde_json::json!({ "lr_gg": 1 }))).unwrap_err().to_string();
        assert!(e.contains("no field `lr_gg`"), "{e}");
        let e = apply(run.clone(), &set(serde_json::json!({ "seed": 1 }))).unwrap_err().to_string();
        assert!(e.contains("fixed"), "{e}");
        let e = apply(run, &set(serde_json::json!({ "generator": { "w_dim": 8 } }))).unwrap_err().to_string();
        assert!(e.contains("only `tet_res`"), "{e}");
    }

    /// The shipped recipe's configs (`configs/*.toml`): their flags are `train`'s and every
    /// change of their schedules applies to a run's settings.
    #[test]
    fn the_shipped_configs_name_real_flags_and_fields() {
        use clap::Args;
        let cmd = crate::train::TrainArgs::augment_args(clap::Command::new("train"));
        let known: Vec<String> = cmd.get_arguments().filter_map(|a| a.get_long().map(String::from)).collect();
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
        let mut files: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
        files.retain(|p| p.extension().is_some_and(|e| e == "toml"));
        assert!(files.len() >= 3, "{files:?}");
        let demo = getavatar_core::generator::network::GeneratorConfig::demo();
        let rc = crate::train::RunConfig::for_tests(demo, crate::train::Objective::Reconstruction);
        for f in files {
            let argv: Vec<OsString> = vec!["trainer".into(), "train".into(), "--cfg".into(), f.clone().into()];
            assert!(expand(argv, &known).unwrap().len() > 4, "{}: no flags", f.display());
            let mut run = serde_json::to_value(&rc).unwrap();
            let sched = schedule(&f).unwrap();
            assert!(!sched.is_empty(), "{}", f.display());
            for e in sched {
                run = apply(run, &e.set).unwrap_or_else(|err| panic!("{}: {err:#}", f.display()));
            }
            let _: crate::train::RunConfig = serde_json::from_value(run).unwrap();
        }
    }
}
