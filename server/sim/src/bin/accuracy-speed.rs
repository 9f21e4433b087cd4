//! The speed–accuracy study (docs/accuracy-speed.md).
//!
//! ```text
//! accuracy-speed                          sweep the settings, write docs/accuracy-speed.{md,svg,json}
//! accuracy-speed export-problems DIR      write the reference problems' meshes for tools/reference
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use cutsim_sim::accuracy::problems::problems;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("export-problems") => match args.get(1) {
            Some(dir) => export_problems(&PathBuf::from(dir)),
            None => Err("export-problems needs the directory to write into".to_string()),
        },
        Some("-h" | "--help") => {
            println!("{}", USAGE);
            Ok(())
        }
        Some(other) => Err(format!("unknown command {other:?}\n{USAGE}")),
        None => Err("the sweep is not written yet".into()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

const USAGE: &str = "usage: accuracy-speed [export-problems DIR]";

fn export_problems(dir: &std::path::Path) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for problem in problems().map_err(|e| e.to_string())? {
        let export = problem.export().map_err(|e| e.to_string())?;
        let path = dir.join(format!("{}.json", problem.name));
        std::fs::write(&path, export.to_string()).map_err(|e| format!("{}: {e}", path.display()))?;
        eprintln!("wrote {} ({} nodes, {} hexahedra)", path.display(), export["nodes"].as_array().map_or(0, |a| a.len()), export["hexes"].as_array().map_or(0, |a| a.len()));
    }
    Ok(())
}
