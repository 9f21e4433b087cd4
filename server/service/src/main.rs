//! `cutsim-server`: the cutsim server binary.
//!
//! `cutsim-server run SCENE [--steps N] [--script SCRIPT.json] [--json]` runs a scene
//! headless in lockstep (optionally driven by a cut script) and prints a report;
//! `cutsim-server scene-schema` prints the JSON Schema of scene files.

mod headless;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "cutsim-server", version, about = "Soft-tissue cutting simulator server")]
struct Cli {
    /// Directory of bundled scenes (repeatable; default: the repository's server/scenes).
    #[arg(long = "scenes-dir", global = true)]
    scenes_dir: Vec<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a scene headless in lockstep (as fast as the CPU allows) and print a report.
    Run(headless::RunArgs),
    /// Print the JSON Schema of scene files.
    SceneSchema,
}

/// Where bundled scenes are looked up: the given directories, else $CUTSIM_SCENES_DIR,
/// else the repository's server/scenes.
pub fn scene_dirs(given: &[PathBuf]) -> Vec<PathBuf> {
    if !given.is_empty() {
        return given.to_vec();
    }
    if let Some(dir) = std::env::var_os("CUTSIM_SCENES_DIR") {
        return std::env::split_paths(&dir).collect();
    }
    vec![PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes"))]
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let dirs = scene_dirs(&cli.scenes_dir);
    match cli.command {
        Command::Run(args) => headless::run(&args, &dirs),
        Command::SceneSchema => {
            println!("{}", serde_json::to_string_pretty(&cutsim_sim::scene::json_schema()).expect("schema is JSON"));
            ExitCode::SUCCESS
        }
    }
}
