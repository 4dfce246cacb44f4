//! The CLI's front page stays short: `trainer --help` lists at most 12 commands (the
//! maintenance ones are hidden but named and still run), and the benchmarks sit behind one
//! `trainer bench <what>`.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;
use common::trainer;

#[test]
fn the_help_lists_at_most_twelve_commands_and_names_the_hidden_ones() {
    let o = trainer(&["--help"]);
    assert!(o.status.success());
    let help = String::from_utf8_lossy(&o.stdout);
    let commands: Vec<&str> = help
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .map(|l| l.split_whitespace().next().unwrap())
        .collect();
    assert!((8..=12).contains(&commands.len()), "{} commands: {commands:?}", commands.len());
    for c in ["bench", "train", "invert", "export", "motion-from-video"] {
        assert!(commands.contains(&c), "{c} missing from {commands:?}");
    }
    for hidden in ["body-model", "plot-losses", "fit-codes", "fit-mapping", "garment-codes", "variety"] {
        assert!(!commands.contains(&hidden) && help.contains(hidden), "{hidden}: {help}");
        assert!(trainer(&[hidden, "--help"]).status.success(), "{hidden} --help");
    }
    let bench = String::from_utf8_lossy(&trainer(&["bench", "--help"]).stdout).to_string();
    for what in ["generator", "train", "export", "fit"] {
        assert!(bench.lines().any(|l| l.trim_start().starts_with(what)), "bench {what}: {bench}");
    }
    assert!(!trainer(&["bench-fit"]).status.success(), "the old bench commands are gone");
}
