//! Recording retention: recordings of closed sessions older than `max_age_days` are
//! deleted, and, while the recordings take more than `max_total_mib`, the oldest of
//! closed sessions go first. A live session's recording is never touched.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use crate::config::RecordingPolicy;

/// Deletes what the policy no longer keeps; returns the files removed.
pub fn sweep(dir: &Path, policy: &RecordingPolicy, live: &[String], now: SystemTime) -> std::io::Result<Vec<PathBuf>> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    // (modified, bytes, path, live)
    let mut files: Vec<(SystemTime, u64, PathBuf, bool)> = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        let Some(session) = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".jsonl")) else { continue };
        let Ok(meta) = entry.metadata() else { continue };
        if !meta.is_file() {
            continue;
        }
        let live = live.iter().any(|l| l == session);
        files.push((meta.modified().unwrap_or(now), meta.len(), path, live));
    }
    files.sort_by_key(|f| f.0);
    let mut removed = Vec::new();
    let mut total: u64 = files.iter().map(|f| f.1).sum();
    let max_age = (policy.max_age_days > 0.0).then(|| Duration::from_secs_f64(policy.max_age_days * 86_400.0));
    let max_total = (policy.max_total_mib > 0.0).then(|| (policy.max_total_mib * 1_048_576.0) as u64);
    for (modified, bytes, path, live) in files {
        if live {
            continue;
        }
        let too_old = max_age.is_some_and(|age| now.duration_since(modified).unwrap_or_default() > age);
        let too_much = max_total.is_some_and(|limit| total > limit);
        if too_old || too_much {
            std::fs::remove_file(&path)?;
            total -= bytes;
            removed.push(path);
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn old_and_excess_recordings_go_oldest_first_and_live_ones_stay() {
        let dir = std::env::temp_dir().join(format!("cutsim-retention-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let now = SystemTime::now();
        let day = Duration::from_secs(86_400);
        let write = |name: &str, bytes: usize, age: Duration| {
            let path = dir.join(format!("{name}.jsonl"));
            std::fs::write(&path, vec![b'x'; bytes]).unwrap();
            std::fs::File::options().write(true).open(&path).unwrap().set_modified(now - age).unwrap();
        };
        write("aaaa", 1000, 40 * day); // older than 30 days
        write("bbbb", 1000, 40 * day); // as old, but live
        write("cccc", 600 << 10, 3 * day);
        write("dddd", 600 << 10, 2 * day);
        write("eeee", 10, day);
        std::fs::write(dir.join("notes.txt"), "not a recording").unwrap();
        let policy = RecordingPolicy { max_age_days: 30.0, max_total_mib: 1.0, ..RecordingPolicy::default() };
        let removed = sweep(&dir, &policy, &["bbbb".into()], now).unwrap();
        let names: Vec<_> = removed.iter().map(|p| p.file_name().unwrap().to_str().unwrap().to_owned()).collect();
        // aaaa is too old; then 1.2 MiB remain over the 1 MiB limit: cccc (the oldest
        // closed one) goes; bbbb is live and stays although it is the oldest.
        assert_eq!(names, ["aaaa.jsonl", "cccc.jsonl"]);
        for kept in ["bbbb.jsonl", "dddd.jsonl", "eeee.jsonl", "notes.txt"] {
            assert!(dir.join(kept).exists(), "{kept} is kept");
        }
        assert!(sweep(&dir.join("missing"), &policy, &[], now).unwrap().is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
