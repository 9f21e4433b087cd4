//! A printable report of one session's task: the verdict, every metric with its unit, the
//! failures and warnings, the plan with the trainee's cut drawn over it (seen from outside
//! the surface), and the force over time. One self-contained HTML file (inline CSS and
//! SVG, no script), so an instructor can save, mail and print it.

use std::fmt::Write;

use super::metrics::{Assessment, History};
use crate::math::across;
use super::task::Task;
use crate::math::Vec3;

/// Who and what the report is about.
pub struct ReportHeader<'a> {
    pub session: &'a str,
    pub scene: &'a str,
    pub task: &'a str,
    /// The server that wrote it.
    pub build: &'a str,
}

/// Figure size, px.
const WIDTH: f64 = 640.0;
const PLAN_HEIGHT: f64 = 320.0;
const FORCE_HEIGHT: f64 = 180.0;
const MARGIN: f64 = 36.0;

pub fn render(header: &ReportHeader, task: &Task, a: &Assessment, history: &History) -> String {
    let mut out = String::with_capacity(16 * 1024);
    let title = format!("Assessment — session {} ({})", header.session, header.scene);
    let _ = write!(
        out,
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title>\n<style>{STYLE}</style></head><body>\n<h1>{}</h1>\n",
        escape(&title),
        escape(&title)
    );
    let _ = writeln!(out, "<p class=\"task\">{}</p>", escape(if header.task.is_empty() { "No task: motion and force metrics only." } else { header.task }));
    let verdict = match a.passed {
        Some(true) => "<span class=\"pass\">passed</span>".to_owned(),
        Some(false) => "<span class=\"fail\">failed</span>".to_owned(),
        None => "no verdict (the scene has no task)".to_owned(),
    };
    let score = a.score.map_or("–".to_owned(), |s| format!("{s:.0} / 100"));
    let _ = writeln!(out, "<p class=\"verdict\">Verdict: {verdict} · score {score} · {} steps assessed</p>", a.steps);
    if !a.failures.is_empty() {
        out.push_str("<ul class=\"failures\">");
        for f in &a.failures {
            let _ = write!(out, "<li>{}</li>", escape(f));
        }
        out.push_str("</ul>\n");
    }

    out.push_str("<h2>The cut against the plan</h2>\n");
    out.push_str(&plan_figure(task, history));
    out.push_str("<h2>Force</h2>\n");
    out.push_str(&force_figure(task, history));

    out.push_str("<h2>Metrics</h2>\n<table><tr><th>metric</th><th>value</th></tr>\n");
    for (name, value) in metric_rows(a) {
        let _ = writeln!(out, "<tr><td>{}</td><td>{}</td></tr>", escape(name), escape(&value));
    }
    out.push_str("</table>\n");
    if !a.events.is_empty() {
        out.push_str("<h2>Events</h2>\n<table><tr><th>time</th><th>what</th></tr>\n");
        for e in &a.events {
            let _ = writeln!(out, "<tr><td>{:.3} s</td><td>{}</td></tr>", e.time_s, escape(&e.message));
        }
        if a.events_dropped > 0 {
            let _ = writeln!(out, "<tr><td></td><td>… and {} more</td></tr>", a.events_dropped);
        }
        out.push_str("</table>\n");
    }
    let _ = writeln!(
        out,
        "<p class=\"foot\">Definitions, weights and sources: docs/assessment.md. Written by {}.</p>\n</body></html>",
        escape(header.build)
    );
    out
}

fn metric_rows(a: &Assessment) -> Vec<(&'static str, String)> {
    let opt = |v: Option<f64>, unit: &str, digits: usize| v.map_or("–".to_owned(), |v| format!("{v:.digits$}{unit}"));
    vec![
        ("time to complete", opt(a.time_to_complete_s, " s", 2)),
        ("coverage of the plan", opt(a.coverage.map(|c| c * 100.0), " %", 0)),
        ("deviation, RMS", opt(a.deviation_rms_mm, " mm", 2)),
        ("deviation, largest", opt(a.deviation_max_mm, " mm", 2)),
        ("cut outside the band", opt(a.outside_band_mm, " mm", 1)),
        ("depth error, RMS", opt(a.depth_error_rms_mm, " mm", 2)),
        ("incision length", format!("{:.1} mm", a.incision_length_mm)),
        ("plan length", opt(a.plan_length_mm, " mm", 1)),
        ("strokes", a.strokes.to_string()),
        ("tool path", format!("{:.1} mm", a.path_length_mm)),
        ("economy of motion", opt(a.economy_of_motion, "", 2)),
        ("peak force", format!("{:.2} N", a.peak_force_n)),
        ("mean force in contact", format!("{:.2} N", a.mean_force_n)),
        ("time above the force limit", opt(a.time_above_force_limit_s, " s", 3)),
        ("peak grip of the forceps", format!("{:.2} N", a.peak_grip_force_n)),
        ("time above the grip limit", opt(a.time_above_grip_limit_s, " s", 3)),
        ("RMS jerk", format!("{:.0} m/s³", a.jerk_rms_m_per_s3)),
        ("log dimensionless jerk", opt(a.log_dimensionless_jerk, "", 2)),
        ("no-go entries", a.no_go_entries.to_string()),
        ("time in no-go regions", format!("{:.3} s", a.no_go_time_s)),
    ]
}

/// A point in the plot's plane, m.
type Point2 = (f64, f64);

/// The plan (its band shaded, the line dashed), the cut path per stroke and the no-go
/// regions, seen along the plan's normal; 10 mm scale bar.
fn plan_figure(task: &Task, history: &History) -> String {
    let normal = task.plan.as_ref().map_or(Vec3::z(), |p| p.normal);
    let plan: Vec<Vec3> = task.plan.as_ref().map_or_else(Vec::new, |p| p.points().to_vec());
    let cut: Vec<(u32, Vec3)> = history.cut_path.iter().map(|(s, p)| (*s, Vec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))).collect();
    // In-surface axes: u along the plan (or x), v = n × u.
    let along = match (plan.first(), plan.last()) {
        (Some(a), Some(b)) => across(&(b - a), &normal),
        _ => across(&Vec3::x(), &normal),
    };
    let u = if along.norm() > 1e-12 { along.normalize() } else { across(&Vec3::y(), &normal).normalize() };
    let v = normal.cross(&u);
    let flat = |p: &Vec3| (p.dot(&u), p.dot(&v));
    let band = task.plan.as_ref().map_or(0.0, |p| p.band_m);
    let mut points: Vec<Point2> = plan.iter().chain(cut.iter().map(|(_, p)| p)).map(flat).collect();
    // Each no-go region's name and its box's lower and upper corners in the plot's plane.
    let boxes: Vec<(String, Point2, Point2)> = task
        .no_go
        .iter()
        .map(|r| {
            let corners: Vec<(f64, f64)> = (0..8)
                .map(|i| flat(&Vec3::new(if i & 1 == 0 { r.min.x } else { r.max.x }, if i & 2 == 0 { r.min.y } else { r.max.y }, if i & 4 == 0 { r.min.z } else { r.max.z })))
                .collect();
            let lo = corners.iter().fold((f64::INFINITY, f64::INFINITY), |m, c| (m.0.min(c.0), m.1.min(c.1)));
            let hi = corners.iter().fold((f64::NEG_INFINITY, f64::NEG_INFINITY), |m, c| (m.0.max(c.0), m.1.max(c.1)));
            (r.name.clone(), lo, hi)
        })
        .collect();
    if points.is_empty() {
        return "<p>Nothing was cut and the task has no planned incision.</p>\n".to_owned();
    }
    for (_, lo, hi) in &boxes {
        points.push(*lo);
        points.push(*hi);
    }
    let (lo, hi) = points.iter().fold(((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY)), |(lo, hi), p| {
        ((lo.0.min(p.0 - band), lo.1.min(p.1 - band)), (hi.0.max(p.0 + band), hi.1.max(p.1 + band)))
    });
    let span = ((hi.0 - lo.0) / (WIDTH - 2.0 * MARGIN)).max((hi.1 - lo.1) / (PLAN_HEIGHT - 2.0 * MARGIN)).max(1e-6);
    let scale = 1.0 / span; // px per m
    let centre = ((lo.0 + hi.0) / 2.0, (lo.1 + hi.1) / 2.0);
    let px = |p: (f64, f64)| (WIDTH / 2.0 + (p.0 - centre.0) * scale, PLAN_HEIGHT / 2.0 - (p.1 - centre.1) * scale);
    let mut svg = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{WIDTH}\" height=\"{PLAN_HEIGHT}\" viewBox=\"0 0 {WIDTH} {PLAN_HEIGHT}\">\n<rect width=\"100%\" height=\"100%\" fill=\"#fbf7f4\"/>\n");
    for (name, lo, hi) in &boxes {
        let (a, b) = (px(*lo), px(*hi));
        let _ = writeln!(
            svg,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"#f0a030\" fill-opacity=\"0.25\" stroke=\"#d07000\"/><text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#a05000\">no-go: {}</text>",
            a.0,
            b.1,
            b.0 - a.0,
            a.1 - b.1,
            a.0 + 3.0,
            b.1 + 12.0,
            escape(name)
        );
    }
    let polyline = |pts: &[Vec3]| pts.iter().map(|p| px(flat(p))).map(|(x, y)| format!("{x:.1},{y:.1}")).collect::<Vec<_>>().join(" ");
    if !plan.is_empty() {
        let _ = writeln!(svg, "<polyline points=\"{}\" fill=\"none\" stroke=\"#30c060\" stroke-opacity=\"0.25\" stroke-width=\"{:.1}\" stroke-linecap=\"round\" stroke-linejoin=\"round\"/>", polyline(&plan), 2.0 * band * scale);
        let _ = writeln!(svg, "<polyline points=\"{}\" fill=\"none\" stroke=\"#108040\" stroke-width=\"1.5\" stroke-dasharray=\"6 4\"/>", polyline(&plan));
    }
    let strokes = cut.iter().map(|(s, _)| *s).max().unwrap_or(0);
    for stroke in 1..=strokes {
        let pts: Vec<Vec3> = cut.iter().filter(|(s, _)| *s == stroke).map(|(_, p)| *p).collect();
        let _ = writeln!(svg, "<polyline points=\"{}\" fill=\"none\" stroke=\"#c01818\" stroke-width=\"2\"/>", polyline(&pts));
    }
    let bar = 0.01 * scale;
    let _ = writeln!(
        svg,
        "<line x1=\"{m}\" y1=\"{y:.1}\" x2=\"{x2:.1}\" y2=\"{y:.1}\" stroke=\"#333\" stroke-width=\"2\"/><text x=\"{m}\" y=\"{ty:.1}\" font-size=\"11\" fill=\"#333\">10 mm</text>",
        m = MARGIN / 2.0,
        y = PLAN_HEIGHT - 12.0,
        x2 = MARGIN / 2.0 + bar,
        ty = PLAN_HEIGHT - 16.0
    );
    let _ = writeln!(svg, "<text x=\"{:.1}\" y=\"14\" font-size=\"11\" fill=\"#333\">green: the plan and its band · red: the blade's cut, by stroke</text>", MARGIN / 2.0);
    svg.push_str("</svg>\n");
    svg
}

/// The largest force per bin over the session, with the task's force limit.
fn force_figure(task: &Task, history: &History) -> String {
    let peaks = &history.force_peaks_n;
    if peaks.is_empty() {
        return "<p>No steps yet.</p>\n".to_owned();
    }
    let top = peaks.iter().copied().fold(0.0f32, f32::max).max(task.force_limit_n.unwrap_or(0.0) as f32).max(0.1) as f64 * 1.1;
    let seconds = peaks.len() as f64 * history.force_bin_s;
    let x = |i: usize| MARGIN + (i as f64 + 0.5) * history.force_bin_s / seconds * (WIDTH - 2.0 * MARGIN);
    let y = |f: f64| FORCE_HEIGHT - MARGIN + -(f / top) * (FORCE_HEIGHT - 1.5 * MARGIN);
    let mut svg = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{WIDTH}\" height=\"{FORCE_HEIGHT}\" viewBox=\"0 0 {WIDTH} {FORCE_HEIGHT}\">\n<rect width=\"100%\" height=\"100%\" fill=\"#f7f8fb\"/>\n");
    let _ = writeln!(svg, "<line x1=\"{MARGIN}\" y1=\"{b:.1}\" x2=\"{r:.1}\" y2=\"{b:.1}\" stroke=\"#555\"/><line x1=\"{MARGIN}\" y1=\"{b:.1}\" x2=\"{MARGIN}\" y2=\"{t:.1}\" stroke=\"#555\"/>", b = y(0.0), r = WIDTH - MARGIN, t = y(top));
    let points: Vec<String> = peaks.iter().enumerate().map(|(i, f)| format!("{:.1},{:.1}", x(i), y(f64::from(*f)))).collect();
    let _ = writeln!(svg, "<polyline points=\"{}\" fill=\"none\" stroke=\"#d08a00\" stroke-width=\"1.5\"/>", points.join(" "));
    if let Some(limit) = task.force_limit_n {
        let _ = writeln!(svg, "<line x1=\"{MARGIN}\" y1=\"{l:.1}\" x2=\"{r:.1}\" y2=\"{l:.1}\" stroke=\"#c01818\" stroke-dasharray=\"5 4\"/><text x=\"{tx:.1}\" y=\"{ty:.1}\" font-size=\"11\" fill=\"#c01818\">limit {limit} N</text>", l = y(limit), r = WIDTH - MARGIN, tx = WIDTH - MARGIN - 70.0, ty = y(limit) - 4.0);
    }
    let _ = writeln!(
        svg,
        "<text x=\"4\" y=\"{:.1}\" font-size=\"11\" fill=\"#333\">{:.2} N</text><text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#333\">{:.1} s</text><text x=\"{MARGIN}\" y=\"14\" font-size=\"11\" fill=\"#333\">largest force on any tool per {:.0} ms</text>",
        y(top) + 10.0,
        top,
        WIDTH - MARGIN - 30.0,
        FORCE_HEIGHT - MARGIN + 16.0,
        seconds,
        history.force_bin_s * 1e3
    );
    svg.push_str("</svg>\n");
    svg
}

/// Text for HTML (element content and attribute values).
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

const STYLE: &str = "body{font:14px/1.4 system-ui,sans-serif;margin:24px auto;max-width:720px;color:#222}\
h1{font-size:20px}h2{font-size:16px;margin-top:20px}table{border-collapse:collapse}\
td,th{padding:2px 10px;border-bottom:1px solid #ddd;text-align:left}td:last-child{text-align:right}\
.pass{color:#108040;font-weight:bold}.fail{color:#c01818;font-weight:bold}.failures{color:#c01818}\
.foot{color:#777;font-size:12px}svg{border:1px solid #ddd}@media print{body{margin:0}}";

#[cfg(test)]
mod tests {
    use super::*;
    use crate::assessment::plan::Plan;
    use crate::assessment::task::NoGoRegion;
    use crate::assessment::{Assessor, ToolSample};

    #[test]
    fn the_report_draws_the_plan_the_cut_and_the_force_and_escapes_text() {
        let plan = Plan::new(&[Vec3::new(-0.02, 0.0, 0.0), Vec3::new(0.02, 0.0, 0.0)], Vec3::z(), 0.002).unwrap();
        let task = Task {
            plan: Some(plan),
            tool: Some(0),
            depth: None,
            no_go: vec![NoGoRegion { name: "<vessel>".into(), min: Vec3::new(0.0, 0.005, -0.01), max: Vec3::new(0.01, 0.01, 0.01), max_force_n: 0.0 }],
            force_limit_n: Some(3.0),
            grip_limit_n: None,
            min_coverage: 0.9,
        };
        let mut assessor = Assessor::new(task.clone(), 1, 0.001);
        for i in 0..=400 {
            let p = Vec3::new(-0.02 + 1e-4 * f64::from(i), 0.001, -0.003);
            assessor.observe(&[ToolSample { position_m: p, force_n: 2.0, contacts: 2, active: true, cutting: true, cut_held: true, grip_force_n: 0.0 }]);
        }
        let header = ReportHeader { session: "abc", scene: "skin-patch", task: "cut <here> & there", build: "test" };
        let html = render(&header, &task, &assessor.assessment(), assessor.history());
        assert!(html.contains("cut &lt;here&gt; &amp; there") && !html.contains("<here>"), "text is escaped");
        assert!(html.contains("no-go: &lt;vessel&gt;"));
        assert!(html.contains("class=\"pass\""), "the verdict");
        assert_eq!(html.matches("<svg").count(), 2, "the plan figure and the force figure");
        assert_eq!(html.matches("stroke=\"#c01818\" stroke-width=\"2\"").count(), 1, "one stroke drawn");
        assert!(html.contains("limit 3 N"));
        assert!(html.contains("<td>deviation, RMS</td><td>1.00 mm</td>"), "{html}");
        assert!(!html.contains("<script"), "no script in the report");
    }
}
