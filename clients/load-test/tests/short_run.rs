//! The load and fault test's short run, as CI runs it: the real `cutsim-load` binary
//! against the real `cutsim-server` beside it (both built by `cargo test --workspace`),
//! two real-time sessions with two viewers each for 8 s, the bot's scripts and every
//! fault case (SIGKILL and restart, a full disk, stalled and garbage clients). The full
//! run (`cutsim-load --report docs/reliability.md`) writes the committed report.
//!
//! It lives here, not as a separate step after the tests, so that it runs the binaries
//! the test build made: a separate `cargo build -p cutsim-load` resolves the workspace's
//! features differently and rebuilt the network stack (about 4 minutes of CI).

use std::path::PathBuf;
use std::process::Command;

#[test]
fn a_short_load_run_with_every_fault_case_passes() {
    // cutsim-load runs the server binary beside its own (target/<profile>/), and says so
    // on stderr, exiting with 2, when it is not there (e.g. `cargo test -p cutsim-load`
    // alone, without `cargo build -p cutsim-server` first).
    let report = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("reliability-short.md");
    let _ = std::fs::remove_file(&report);
    let output = Command::new(env!("CARGO_BIN_EXE_cutsim-load"))
        .args(["--sessions", "2", "--viewers", "2", "--seconds", "8", "--report"])
        .arg(&report)
        .output()
        .expect("cutsim-load runs");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "cutsim-load failed ({}):\n{stderr}", output.status);
    let written = std::fs::read_to_string(&report).unwrap_or_else(|e| panic!("{}: {e}", report.display()));
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert_eq!(written, stdout, "the report file is what was printed");
    assert!(written.contains("**Result: every check passed.**"), "the report's verdict:\n{written}");
    assert!(written.contains("| SIGKILL + restart: session"), "the report has the restart case:\n{written}");
}
