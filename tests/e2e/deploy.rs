//! Deployment: docker/Dockerfile repeats the README's set-up (scripts/run.sh) step for
//! step and copies exactly what those steps make and the server reads; its HEALTHCHECK
//! (`cutsim-server health`) answers from the real gRPC health service. Docker itself
//! cannot run on this project's machines, so the equality is checked on the files.

use std::collections::BTreeSet;
use std::process::Command;

use crate::harness::*;

fn read(relative: &str) -> String {
    std::fs::read_to_string(repo(relative)).unwrap_or_else(|e| panic!("{relative}: {e}"))
}

/// The set-up commands (npm and cargo builds) in the order they run.
fn is_setup(command: &str) -> bool {
    command.contains("npm ci") || command.contains("cargo build")
}

/// scripts/run.sh's set-up commands, `(cd X && C)` written as `cd X && C`.
fn run_sh_steps() -> Vec<String> {
    read("scripts/run.sh")
        .lines()
        .map(str::trim)
        .filter(|l| !l.starts_with('#') && !l.starts_with("echo") && is_setup(l))
        .map(|l| l.trim_start_matches('(').trim_end_matches(')').to_string())
        .collect()
}

/// The Dockerfile's instructions, continuation lines joined.
fn dockerfile_instructions() -> Vec<String> {
    let text = read("docker/Dockerfile");
    let mut out = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('#') || (line.is_empty() && current.is_empty()) {
            continue;
        }
        match line.strip_suffix('\\') {
            Some(head) => current.push_str(head),
            None => {
                current.push_str(line);
                if !current.is_empty() {
                    out.push(std::mem::take(&mut current));
                }
            }
        }
    }
    out
}

#[test]
fn the_dockerfile_repeats_the_readme_set_up_and_copies_what_it_makes() {
    let docker = dockerfile_instructions();
    let docker_steps: Vec<String> = docker.iter().filter_map(|i| i.strip_prefix("RUN ")).filter(|c| is_setup(c)).map(str::to_string).collect();
    let readme_steps = run_sh_steps();
    assert!(readme_steps.len() >= 2, "scripts/run.sh has its set-up steps: {readme_steps:?}");
    assert_eq!(docker_steps, readme_steps, "docker/Dockerfile's build steps differ from scripts/run.sh's");

    // What the runtime image copies from the build: the binaries the cargo step builds,
    // and the directories the server and the bot read.
    let build = readme_steps.iter().find(|s| s.contains("cargo build")).unwrap();
    let packages: Vec<&str> = build.split_whitespace().collect::<Vec<_>>().windows(2).filter(|w| w[0] == "-p").map(|w| w[1]).collect();
    let mut expected: BTreeSet<String> = packages.iter().map(|p| format!("target/release/{p}")).collect();
    for dir in ["web-viewer", "server/scenes", "clients/cut-bot/examples"] {
        assert!(repo(dir).is_dir(), "{dir} is in the repository");
        expected.insert(dir.to_string());
    }
    let mut copies = std::collections::BTreeMap::new();
    for instruction in &docker {
        if let Some(rest) = instruction.strip_prefix("COPY --from=build /src/") {
            let mut parts = rest.split_whitespace();
            copies.insert(parts.next().unwrap().to_string(), parts.next().expect("a destination").to_string());
        }
    }
    assert_eq!(copies.keys().cloned().collect::<BTreeSet<_>>(), expected, "the runtime image copies exactly what the set-up makes and the server reads");

    // The config the image runs with points at those copies.
    let config: serde_json::Value = serde_json::from_str(&read("docker/server.json")).unwrap();
    assert_eq!(config["viewer_dir"], copies["web-viewer"].as_str());
    assert_eq!(config["scene_dirs"][0], copies["server/scenes"].as_str());
    assert!(docker.iter().any(|i| i.starts_with("RUN ") && i.contains(config["recordings_dir"].as_str().unwrap())), "the image makes the recordings directory");
    assert!(docker.iter().any(|i| i == "COPY docker/server.json /etc/cutsim/server.json"));
    // A non-root user, and a health check through the gRPC health service.
    assert!(docker.iter().any(|i| i.starts_with("USER ") && !i.ends_with("root")));
    let health = docker.iter().find(|i| i.starts_with("HEALTHCHECK")).expect("a HEALTHCHECK");
    assert!(health.contains(r#""cutsim-server", "health""#), "{health}");
    // The k8s probes ask the same service.
    let k8s = read("docker/k8s/deployment.yaml");
    assert!(k8s.contains("readinessProbe:") && k8s.contains("grpc: { port: 50051 }"));
}

#[test]
fn the_health_command_reports_a_serving_server_and_fails_without_one() {
    let server = Server::start();
    let out = Command::new(server_binary()).args(["health", "--grpc-addr", &server.grpc]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("serving"));
    // A port nobody listens on.
    let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    let out = Command::new(server_binary()).args(["health", "--grpc-addr", &free.to_string(), "--timeout-s", "2"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no answer"), "{}", String::from_utf8_lossy(&out.stderr));
}
