//! The study's results and their rendering: docs/accuracy-speed.md (tables),
//! docs/accuracy-speed.svg (error against p99 step time, Pareto fronts, the 1 ms line)
//! and docs/accuracy-speed.json (what `"fidelity": "auto"` quotes as error class).

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use super::sweep::{Setting, StepTiming};

/// A measured setting.
#[derive(Debug, Clone)]
pub struct Row {
    pub setting: Setting,
    /// Err: the scene refused the setting at load (the reason).
    pub outcome: Result<Measured, String>,
}

#[derive(Debug, Clone, Copy)]
pub struct Measured {
    pub timing: StepTiming,
    /// Static displacement error (relative rms) against the scene's reference: the
    /// level's linear solution to 1e-10 without the ghost (discretization only).
    pub static_error: Option<f64>,
    /// What a session computes: the grid as built (ghost included) settled under gravity
    /// by its own dynamics at the scene's cap and tolerance, against the same reference.
    /// None where the level's steps are too slow to settle in the study's time.
    pub session_error: Option<f64>,
    /// First-frequency error (relative) against the reference (cantilever only).
    pub frequency_error: Option<f64>,
    pub elements: usize,
    pub voxels: usize,
    pub triangles: usize,
    /// Fixed nodes: the support a level resolves changes with it.
    pub held_nodes: usize,
}

impl Measured {
    /// The error the plot and the Pareto front use: the worse of the two.
    pub fn error(&self) -> Option<f64> {
        match (self.static_error, self.frequency_error) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        }
    }
}

/// One scene's study.
#[derive(Debug, Clone)]
pub struct SceneStudy {
    pub scene: String,
    pub description: String,
    pub reference: String,
    pub rows: Vec<Row>,
    /// (level, condensed error, fill-ratio error, fully integrated condensed error).
    pub weighting: Vec<(u32, f64, f64, f64)>,
}

/// The corotational model at growing loads (settled under strong damping) against the
/// linear reference scaled to the load.
#[derive(Debug, Clone, Copy)]
pub struct LoadRow {
    pub gravity_multiple: f64,
    pub tip_deflection_over_length: f64,
    pub error: f64,
}

/// The mass-spring skin's checks (see [`super::membrane`]).
#[derive(Debug, Clone)]
pub struct MembraneStudy {
    pub stretch: super::membrane::Stretch,
    /// (εr, peak gap m, peak step, plateau gap m).
    pub shrinking: Vec<(f64, f64, usize, f64)>,
}

/// The machine-readable summary: per scene and level, the static error measured.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ErrorTable {
    pub scenes: Vec<SceneErrors>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneErrors {
    pub scene: String,
    pub reference: String,
    /// (level, static error, relative rms).
    pub levels: Vec<(u32, f64)>,
}

impl ErrorTable {
    pub fn from_studies(studies: &[SceneStudy]) -> Self {
        let scenes = studies
            .iter()
            .map(|s| {
                // Every row of a level has the level's static error.
                let mut levels = std::collections::BTreeMap::new();
                for row in &s.rows {
                    if let Some(e) = row.outcome.as_ref().ok().and_then(|m| m.static_error) {
                        levels.insert(row.setting.level, e);
                    }
                }
                SceneErrors { scene: s.scene.clone(), reference: s.reference.clone(), levels: levels.into_iter().collect() }
            })
            .collect();
        ErrorTable { scenes }
    }

    /// The error measured for a scene at a level, and what it was measured against.
    pub fn lookup(&self, scene: &str, level: u32) -> Option<(f64, &str)> {
        let s = self.scenes.iter().find(|s| s.scene == scene)?;
        s.levels.iter().find(|(l, _)| *l == level).map(|(_, e)| (*e, s.reference.as_str()))
    }
}

/// The error class a fidelity report quotes.
pub fn error_class(error: f64) -> &'static str {
    match error {
        e if e < 0.02 => "fine (< 2 % displacement error)",
        e if e < 0.10 => "good (2–10 %)",
        e if e < 0.25 => "coarse (10–25 %)",
        _ => "rough (> 25 %)",
    }
}

/// A load refusal, short: the iterations it needs, or the message without its origin.
fn short_refusal(message: &str) -> String {
    let needs = message.split("needs ").nth(1).and_then(|t| t.split(' ').next()).and_then(|n| n.parse::<u32>().ok());
    let cap = message.split("more than the ").nth(1).and_then(|t| t.split(' ').next()).and_then(|n| n.parse::<u32>().ok());
    match (needs, cap) {
        (Some(n), Some(c)) => format!("refused at load: the solve needs {n} CG iterations, {c} allowed"),
        _ => format!("refused at load: {}", message.rsplit(": ").next().unwrap_or(message)),
    }
}

fn percent(e: Option<f64>) -> String {
    match e {
        None => "–".into(),
        Some(0.0) => "0 (the reference)".into(),
        Some(e) => format!("{:.2} %", 100.0 * e),
    }
}

/// Indices of the rows on the Pareto front (no other row is both faster at p99 and
/// more accurate), fastest first.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0).then(points[a].1.total_cmp(&points[b].1)));
    let mut front = Vec::new();
    let mut best = f64::INFINITY;
    for i in order {
        if points[i].1 < best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

/// The Markdown report.
pub fn markdown(studies: &[SceneStudy], loads: &[LoadRow], membrane: &MembraneStudy, reference_check: &[String], command: &str, machine: &str) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Speed against accuracy\n");
    let _ = writeln!(md, "Generated by `{command}` on {machine}; do not edit by hand. Step times vary by up to 40 % between hours on this 2-core machine.\n");
    let _ = writeln!(md, "![Error against p99 step time](accuracy-speed.svg)\n");
    let _ = writeln!(
        md,
        "**Error** is the static displacement error under gravity (relative rms over the sample points: every node of the level-0 mesh, or every 16th on large bodies) of the level's linear solution (its discretization error) against the finest reference there is for the scene; **session error** is that of what a session computes — the grid as built, ghost material included, settled by its own dynamics (mass damping 30/s, until no node moves faster than 10 µm/s per unit of load scale, at most 4 s) at the setting's iteration cap and the scene's tolerance — against the same reference, where a level's steps are fast enough to settle (p50 under 30 ms). The session is loaded with gravity scaled down until the linear reference's largest displacement is 0.5 % of the body's size, and its displacements scaled back up: at full gravity the soft livers' linear solutions move farther than the livers are long (0.74 m on `liver`), where the corotational session gives a large-rotation answer that the linear reference cannot judge. Elements are mean-dilatation (the default) unless a table says otherwise; on the cantilever it is the worse of that and the error of the first frequency that the dynamics deliver (released from rest without damping, the period between the tip's turning points) against scikit-fem's eigenvalue. **Step time** is one physics step with a probe pressed 4 mm into the body's top (contacts every step), after a warm-up. Mass model and CG cap do not change the static equilibrium, so their rows share the level's static error; they change the dynamics (the cantilever's frequency column) and the step time. A body held by a box (the livers) is held by the nodes a level has inside it: coarser levels hold fewer, farther apart (the held-nodes column), and part of their error is that changed support.\n"
    );
    let _ = writeln!(md, "## The level-0 model against scikit-fem\n");
    let _ = writeln!(md, "Same mesh, same trilinear elements (linear, small-strain mode) — fully integrated against scikit-fem's Hex1, mean dilatation against its Hex1 with a constant pressure per hexahedron (Hex1–P0) — so only round-off and solver tolerance may differ (`cargo test -p cutsim-sim --test reference` asserts < 1e-6):\n");
    for line in reference_check {
        let _ = writeln!(md, "- {line}");
    }
    for study in studies {
        let _ = writeln!(md, "\n## {}\n\n{}\n\nReference: {}.\n", study.scene, study.description, study.reference);
        let _ = writeln!(md, "| setting | step p50 | step p99 | static error | session error | frequency error | elements | voxels | triangles | held nodes | CG/step |");
        let _ = writeln!(md, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        for row in &study.rows {
            match &row.outcome {
                Ok(m) => {
                    let _ = writeln!(
                        md,
                        "| {} | {:.0} µs | {:.0} µs | {} | {} | {} | {} | {} | {} | {} | {:.1} |",
                        row.setting.label(),
                        m.timing.p50_us,
                        m.timing.p99_us,
                        percent(m.static_error),
                        percent(m.session_error),
                        percent(m.frequency_error),
                        m.elements,
                        m.voxels,
                        m.triangles,
                        m.held_nodes,
                        m.timing.mean_cg
                    );
                }
                Err(reason) => {
                    let _ = writeln!(md, "| {} | {} |||||||||| ", row.setting.label(), short_refusal(reason).replace('|', "/"));
                }
            }
        }
        if !study.weighting.is_empty() {
            let _ = writeln!(
                md,
                "\nThe coarse elements' stiffness, same coarse elements, linear static error: condensed from the voxels with mean dilatation (the default), condensed from fully integrated voxels (the paper's element: every voxel's volume constraint inherited), and the full cell's fully integrated stiffness times the fraction of it filled (fill-ratio weighting, common in sparse grids):\n"
            );
            let _ = writeln!(md, "| level | condensed, mean dilatation | condensed, fully integrated | fill ratio | closest |");
            let _ = writeln!(md, "|---:|---:|---:|---:|---|");
            for &(level, mean_dilatation, full, fill) in &study.weighting {
                let closest = if mean_dilatation <= full.min(fill) {
                    "mean dilatation"
                } else if (full - fill).abs() < 1e-9 {
                    "fully integrated (every cell full)"
                } else if full < fill {
                    "fully integrated"
                } else {
                    "fill ratio"
                };
                let _ = writeln!(md, "| {level} | {:.2} % | {:.2} % | {:.2} % | {closest} |", 100.0 * mean_dilatation, 100.0 * full, 100.0 * fill);
            }
        }
    }
    if !loads.is_empty() {
        let _ = writeln!(md, "\n## The corotational model at growing loads\n");
        let _ = writeln!(
            md,
            "The cantilever at level 1 under a multiple of gravity, settled by the dynamics (heavy damping, 1.5 s), against the linear Hex2 solution scaled to the load. At small loads the difference is the level's discretization error; as the deflection grows, the corotational model departs from the linear one (rotations the linear model cannot represent), so beyond a few percent of the length the linear reference stops being a reference for the large-deflection answer.\n"
        );
        let _ = writeln!(md, "| load | tip deflection / length | difference from linear |");
        let _ = writeln!(md, "|---:|---:|---:|");
        for l in loads {
            let _ = writeln!(md, "| {} g | {:.2} % | {:.2} % |", l.gravity_multiple, 100.0 * l.tip_deflection_over_length, 100.0 * l.error);
        }
    }
    let s = &membrane.stretch;
    let _ = writeln!(md, "\n## The mass-spring skin\n");
    let _ = writeln!(
        md,
        "Uniaxial stretch of the calibrated patch (10 × 10 cm, 5 mm equilateral mesh, E = {:.0} kPa, 2 mm thick; pulled 1 % on rollers, relaxed): the springs reproduce **E = {:.0} Pa ({:+.2} % of the membrane's)** and an effective Poisson ratio of {:.3} (an equilateral spring lattice tends to 1/3 whatever the membrane's ν: the model's structural limit here).\n",
        s.young_target_pa / 1e3,
        s.young_measured_pa,
        100.0 * (s.young_measured_pa / s.young_target_pa - 1.0),
        s.poisson
    );
    let _ = writeln!(md, "The shrinking effect (paper Section 2.1, Fig. 6): the gap between the middle lip vertices of a 4 cm incision in a 10 × 8 cm patch held at its edges, after the cut, against the residual strain εr:\n");
    let _ = writeln!(md, "| εr | peak gap | at | plateau (last 100 ms) |");
    let _ = writeln!(md, "|---:|---:|---:|---:|");
    for &(eps, peak, at, plateau) in &membrane.shrinking {
        let at = if peak > 1e-9 { format!("{at} ms") } else { "–".into() };
        let _ = writeln!(md, "| {eps} | {:.3} mm | {at} | {:.3} mm |", peak * 1e3, plateau * 1e3);
    }
    md
}

/// The plot: error (log) against p99 step time (log), one colour per scene, its Pareto
/// front joined, the 1 ms budget as a vertical line.
pub fn svg(studies: &[SceneStudy]) -> String {
    const W: f64 = 800.0;
    const H: f64 = 480.0;
    const LEFT: f64 = 70.0;
    const RIGHT: f64 = 230.0;
    const TOP: f64 = 30.0;
    const BOTTOM: f64 = 50.0;
    let colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"];
    let points: Vec<Vec<(f64, f64)>> = studies
        .iter()
        // The reference setting itself (error 0 by construction) has no place on a log axis.
        .map(|s| s.rows.iter().filter_map(|r| r.outcome.as_ref().ok()).filter_map(|m| m.error().filter(|&e| e > 1e-9).map(|e| (m.timing.p99_us / 1e3, e))).collect())
        .collect();
    let all: Vec<(f64, f64)> = points.iter().flatten().copied().collect();
    // Whole decades around the points (and around 1 ms, which is always drawn).
    let decade_below = |v: f64| 10f64.powf(v.log10().floor());
    let decade_above = |v: f64| 10f64.powf(v.log10().ceil());
    let (mut t_lo, mut t_hi) = (0.01f64, 1000.0f64);
    let (mut e_lo, mut e_hi) = (1e-3f64, 1.0f64);
    if !all.is_empty() {
        t_lo = decade_below(all.iter().map(|p| p.0).fold(1.0, f64::min));
        t_hi = decade_above(all.iter().map(|p| p.0).fold(1.0, f64::max));
        e_lo = decade_below(all.iter().map(|p| p.1).fold(f64::INFINITY, f64::min));
        e_hi = decade_above(all.iter().map(|p| p.1).fold(0.0, f64::max));
    }
    let decades = |lo: f64, hi: f64| std::iter::successors(Some(lo), |d| Some(d * 10.0)).take_while(move |d| *d <= hi * 1.0001);
    let x = |t: f64| LEFT + (t.log10() - t_lo.log10()) / (t_hi.log10() - t_lo.log10()) * (W - LEFT - RIGHT);
    let y = |e: f64| TOP + (e_hi.log10() - e.log10()) / (e_hi.log10() - e_lo.log10()) * (H - TOP - BOTTOM);
    let mut s = String::new();
    let _ = writeln!(s, r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="12">"#);
    let _ = writeln!(s, r#"<rect width="{W}" height="{H}" fill="white"/>"#);
    let (x0, x1, y0, y1) = (LEFT, W - RIGHT, TOP, H - BOTTOM);
    for decade in decades(t_lo, t_hi) {
        let xd = x(decade);
        let _ = writeln!(s, r##"<line x1="{xd:.1}" y1="{y0}" x2="{xd:.1}" y2="{y1}" stroke="#ddd"/><text x="{xd:.1}" y="{:.1}" text-anchor="middle">{}</text>"##, y1 + 16.0, fmt_tick(decade));
    }
    for decade in decades(e_lo, e_hi) {
        let yd = y(decade);
        let _ = writeln!(s, r##"<line x1="{x0}" y1="{yd:.1}" x2="{x1}" y2="{yd:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"##, x0 - 6.0, yd + 4.0, fmt_tick(100.0 * decade) + " %");
    }
    let _ = writeln!(s, r##"<rect x="{x0}" y="{y0}" width="{:.1}" height="{:.1}" fill="none" stroke="#444"/>"##, x1 - x0, y1 - y0);
    let budget = x(1.0);
    let _ = writeln!(s, r##"<line x1="{budget:.1}" y1="{y0}" x2="{budget:.1}" y2="{y1}" stroke="#000" stroke-dasharray="6 4" stroke-width="1.5"/><text x="{:.1}" y="{:.1}">1 ms (1 kHz)</text>"##, budget + 4.0, y0 + 14.0);
    let _ = writeln!(s, r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">p99 step time, ms (log)</text>"#, (x0 + x1) / 2.0, H - 10.0);
    let _ = writeln!(s, r#"<text transform="translate(16 {:.1}) rotate(-90)" text-anchor="middle">error vs reference (log)</text>"#, (y0 + y1) / 2.0);
    for (i, (study, pts)) in studies.iter().zip(&points).enumerate() {
        let colour = colours[i % colours.len()];
        let front = pareto_front(pts);
        let path: Vec<String> = front.iter().map(|&k| format!("{:.1},{:.1}", x(pts[k].0), y(pts[k].1))).collect();
        if path.len() > 1 {
            let _ = writeln!(s, r#"<polyline points="{}" fill="none" stroke="{colour}" stroke-width="2"/>"#, path.join(" "));
        }
        for (k, p) in pts.iter().enumerate() {
            let on_front = front.contains(&k);
            let _ = writeln!(
                s,
                r#"<circle cx="{:.1}" cy="{:.1}" r="{}" fill="{}" stroke="{colour}" stroke-width="1.5"/>"#,
                x(p.0),
                y(p.1),
                if on_front { 4.5 } else { 3.0 },
                if on_front { colour } else { "white" }
            );
        }
        let ly = TOP + 10.0 + 20.0 * i as f64;
        let name = if pts.is_empty() { format!("{} (no reference)", study.scene) } else { study.scene.clone() };
        let _ = writeln!(s, r#"<circle cx="{:.1}" cy="{ly:.1}" r="4.5" fill="{colour}"/><text x="{:.1}" y="{:.1}">{name}</text>"#, x1 + 16.0, x1 + 26.0, ly + 4.0);
    }
    let ly = TOP + 10.0 + 20.0 * studies.len() as f64;
    let _ = writeln!(s, r##"<text x="{:.1}" y="{:.1}" fill="#444">filled, joined: Pareto front</text>"##, x1 + 10.0, ly + 4.0);
    s.push_str("</svg>\n");
    s
}

fn fmt_tick(v: f64) -> String {
    if v >= 1.0 { format!("{v:.0}") } else { format!("{v}") }
}
