//! `cut-bot record`: a session recording (written by cutsim-server, format in
//! docs/server.md) into a cut script that reproduces it step for step — commands as
//! keyframes at their steps, held until the next change — with the recorded state hash as
//! its expectation, so that a trainee's session becomes a regression test.

use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::PathBuf;

use anyhow::{Context, anyhow, bail};
use serde_json::{Value, json};

#[derive(clap::Args)]
pub struct RecordArgs {
    /// A recording (recordings/<session>.jsonl).
    recording: PathBuf,
    /// Where to write the script (default: stdout).
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Which tissue lifetime to take when the recording has resets (scripts reset the
    /// session), 0-based; default: the last one that ran any step.
    #[arg(long)]
    epoch: Option<usize>,
    /// Also write the recorded scene to this file and make the script use it (for scenes
    /// that were given inline rather than by a bundled name).
    #[arg(long)]
    scene_out: Option<PathBuf>,
}

#[derive(Default)]
struct Epoch {
    /// (step, tool, command line)
    commands: Vec<(u64, usize, Value)>,
    checkpoints: BTreeMap<u64, String>,
    steps: u64,
}

pub fn run(args: &RecordArgs) -> anyhow::Result<()> {
    let file = std::fs::File::open(&args.recording).with_context(|| format!("cannot open {}", args.recording.display()))?;
    let mut lines = std::io::BufReader::new(file).lines();
    let header: Value = serde_json::from_str(&lines.next().ok_or_else(|| anyhow!("{}: empty recording", args.recording.display()))??)
        .with_context(|| format!("{}: line 1 is not a recording header", args.recording.display()))?;
    if header["format"] != "cutsim-recording" || header["version"] != 1 {
        bail!("{}: not a cutsim recording (version 1)", args.recording.display());
    }
    let scene = &header["scene"];
    let tool_names: Vec<String> = scene["tools"].as_array().into_iter().flatten().map(|t| t["name"].as_str().unwrap_or_default().to_owned()).collect();
    let mut epochs = vec![Epoch::default()];
    let mut lost = 0;
    for (index, line) in lines.enumerate() {
        let number = index + 2;
        let Ok(text) = line else { break };
        let Ok(event) = serde_json::from_str::<Value>(&text) else { break }; // a line cut short by a crash
        let epoch = epochs.last_mut().expect("always one");
        let step = event["step"].as_u64().unwrap_or(0);
        match event["t"].as_str() {
            Some("cmd") => {
                let tool = event["tool"].as_u64().ok_or_else(|| anyhow!("line {number}: a command without a tool"))? as usize;
                if tool >= tool_names.len() {
                    bail!("line {number}: tool {tool} does not exist in the recorded scene");
                }
                epoch.commands.push((step, tool, event));
                epoch.steps = epoch.steps.max(step);
            }
            Some("check") => {
                epoch.checkpoints.insert(step, event["hash"].as_str().unwrap_or_default().to_owned());
                epoch.steps = epoch.steps.max(step);
            }
            Some("reset") => {
                epoch.steps = epoch.steps.max(step);
                epochs.push(Epoch::default());
            }
            Some("end") => epoch.steps = epoch.steps.max(step),
            Some("lost") => lost += event["count"].as_u64().unwrap_or(0),
            other => bail!("line {number}: unknown recording event {other:?}"),
        }
    }
    if lost > 0 {
        bail!("the recording lost {lost} events; a script made from it would not reproduce the session");
    }
    let chosen = match args.epoch {
        Some(k) if k < epochs.len() => k,
        Some(k) => bail!("the recording has tissue lifetimes 0 to {}; --epoch {k} is not one", epochs.len() - 1),
        None => epochs.iter().rposition(|e| e.steps > 0).unwrap_or(0),
    };
    let epoch = &epochs[chosen];

    let mut tracks: BTreeMap<usize, Vec<Value>> = BTreeMap::new();
    let mut per_tool: BTreeMap<usize, Vec<&(u64, usize, Value)>> = BTreeMap::new();
    for command in &epoch.commands {
        per_tool.entry(command.1).or_default().push(command);
    }
    for (tool, commands) in per_tool {
        let keys = tracks.entry(tool).or_default();
        for (i, (step, _, c)) in commands.iter().enumerate() {
            let keyframe = |at: u64| {
                let mut key = json!({ "step": at, "position_m": c["p"], "orientation_wxyz": c["q"], "cut": c["cut"], "active": c["active"] });
                // An analog gripper's squeeze, where the device sent one.
                if let Some(grip) = c.get("grip") {
                    key["grip"] = grip.clone();
                }
                key
            };
            keys.push(keyframe(*step));
            // A command holds until the next one: pin it on the step before, so the
            // script does not interpolate where the session did not move.
            if let Some((next, _, _)) = commands.get(i + 1)
                && *next > step + 1
            {
                keys.push(keyframe(next - 1));
            }
        }
    }
    let scene_ref = match &args.scene_out {
        Some(path) => {
            std::fs::write(path, serde_json::to_string_pretty(scene)?).with_context(|| format!("cannot write {}", path.display()))?;
            path.display().to_string()
        }
        None => scene["name"].as_str().unwrap_or_default().to_owned(),
    };
    let mut expect = serde_json::Map::new();
    if let Some(hash) = epoch.checkpoints.get(&epoch.steps) {
        expect.insert("state_hash".into(), json!(hash));
    }
    let script = json!({
        "scene": scene_ref,
        "steps": epoch.steps,
        "tools": tracks.into_iter().map(|(tool, keyframes)| json!({ "tool": tool_names[tool], "keyframes": keyframes })).collect::<Vec<_>>(),
        "expect": expect,
    });
    let text = serde_json::to_string_pretty(&script)? + "\n";
    match &args.output {
        Some(path) => std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?,
        None => print!("{text}"),
    }
    if !epoch.checkpoints.contains_key(&epoch.steps) {
        eprintln!("note: the recording has no state hash at step {}; the script checks no hash (ask the server for one with GetSession with_state_hash)", epoch.steps);
    }
    Ok(())
}
