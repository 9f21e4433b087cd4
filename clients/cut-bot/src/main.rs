//! `cut-bot`: arrives with the clients issue; until then it says so and exits.

fn main() -> std::process::ExitCode {
    eprintln!("cut-bot is not available yet in this build of cutsim");
    std::process::ExitCode::from(2)
}
