//! JUnit XML for CI systems: one test suite per script, one test case per expectation.

use std::fmt::Write;
use std::time::Duration;

use cutsim_proto::v1 as pb;

pub fn render(script: &str, report: &pb::ScriptReport, elapsed: Duration) -> String {
    let failures = report.expectations.iter().filter(|e| !e.passed).count();
    let tests = report.expectations.len();
    let seconds = elapsed.as_secs_f64();
    let mut out = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(out, "<testsuites name=\"cut-bot\" tests=\"{tests}\" failures=\"{failures}\" time=\"{seconds:.3}\">");
    let _ = writeln!(out, "  <testsuite name=\"{}\" tests=\"{tests}\" failures=\"{failures}\" errors=\"0\" time=\"{seconds:.3}\">", escape(script));
    let _ = writeln!(out, "    <properties>");
    for (name, value) in [
        ("scene", report.scene.clone()),
        ("model", report.model.clone()),
        ("steps", report.steps.to_string()),
        ("state_hash", report.state_hash.clone()),
        ("cuts", report.cuts.to_string()),
        ("incision_length_m", report.incision_length_m.to_string()),
        ("max_tool_force_n", report.max_tool_force_n.to_string()),
    ]
    .into_iter()
    .chain(assessment_properties(report.assessment.as_ref()))
    .map(|(name, value)| (name.to_owned(), value))
    .chain(report.tools.iter().flat_map(|t| {
        [
            (format!("max_force_n.{}", t.name), t.max_force_n.to_string()),
            (format!("grasping_s.{}", t.name), t.grasping_s.to_string()),
            (format!("max_jaws_force_n.{}", t.name), t.max_jaws_force_n.to_string()),
        ]
    }))
    {
        let _ = writeln!(out, "      <property name=\"{name}\" value=\"{}\"/>", escape(&value));
    }
    let _ = writeln!(out, "    </properties>");
    for e in &report.expectations {
        let name = escape(&e.name);
        if e.passed {
            let _ = writeln!(out, "    <testcase classname=\"cut-bot.{}\" name=\"{name}\" time=\"0\"/>", escape(script));
        } else {
            let mut message = format!("expected {}, got {}", e.expected, e.actual);
            if e.name == "reconstruction_fallbacks" {
                // Why each update fell back is what whoever reads the failure needs next.
                for f in &report.fallbacks {
                    let _ = write!(message, "; step {}: {}", f.step, f.reason);
                }
            }
            let message = escape(&message);
            let _ = writeln!(out, "    <testcase classname=\"cut-bot.{}\" name=\"{name}\" time=\"0\">", escape(script));
            let _ = writeln!(out, "      <failure message=\"{message}\" type=\"expectation\">{message}</failure>");
            let _ = writeln!(out, "    </testcase>");
        }
    }
    let _ = writeln!(out, "  </testsuite>\n</testsuites>");
    out
}

/// The task's metrics, each as `assessment.<metric>` (those the task defines).
fn assessment_properties(a: Option<&pb::Assessment>) -> Vec<(&'static str, String)> {
    let Some(a) = a else { return Vec::new() };
    let optional = |name: &'static str, v: Option<f64>| v.map(|v| (name, v.to_string()));
    [
        optional("assessment.score", a.score),
        a.passed.map(|p| ("assessment.passed", p.to_string())),
        Some(("assessment.completed", a.completed.to_string())),
        optional("assessment.time_to_complete_s", a.time_to_complete_s),
        optional("assessment.coverage", a.coverage),
        optional("assessment.deviation_rms_mm", a.deviation_rms_mm),
        optional("assessment.deviation_max_mm", a.deviation_max_mm),
        optional("assessment.outside_band_mm", a.outside_band_mm),
        optional("assessment.depth_error_rms_mm", a.depth_error_rms_mm),
        Some(("assessment.incision_length_mm", a.incision_length_mm.to_string())),
        Some(("assessment.strokes", a.strokes.to_string())),
        Some(("assessment.path_length_mm", a.path_length_mm.to_string())),
        optional("assessment.economy_of_motion", a.economy_of_motion),
        Some(("assessment.peak_force_n", a.peak_force_n.to_string())),
        Some(("assessment.mean_force_n", a.mean_force_n.to_string())),
        optional("assessment.time_above_force_limit_s", a.time_above_force_limit_s),
        Some(("assessment.peak_grip_force_n", a.peak_grip_force_n.to_string())),
        optional("assessment.time_above_grip_limit_s", a.time_above_grip_limit_s),
        optional("assessment.log_dimensionless_jerk", a.log_dimensionless_jerk),
        Some(("assessment.no_go_entries", a.no_go_entries.to_string())),
        (!a.failures.is_empty()).then(|| ("assessment.failures", a.failures.join("; "))),
    ]
    .into_iter()
    .flatten()
    .collect()
}

fn escape(s: &str) -> String {
    s.chars()
        .filter(|c| !c.is_control() || *c == '\n' || *c == '\t')
        .map(|c| match c {
            '&' => "&amp;".to_owned(),
            '<' => "&lt;".to_owned(),
            '>' => "&gt;".to_owned(),
            '"' => "&quot;".to_owned(),
            '\'' => "&apos;".to_owned(),
            c => c.to_string(),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_fallback_expectation_names_each_fallback_and_why() {
        let report = pb::ScriptReport {
            expectations: vec![pb::ExpectationResult { name: "reconstruction_fallbacks".into(), expected: "= 0".into(), actual: "1".into(), passed: false }],
            fallbacks: vec![pb::CutFallback { step: 545, reason: "the removed area meets the mesh border 1 times near the incision's start (0 or 2 supported)".into() }],
            ..Default::default()
        };
        let xml = render("edge.json", &report, Duration::from_secs(1));
        assert!(
            xml.contains("message=\"expected = 0, got 1; step 545: the removed area meets the mesh border 1 times near the incision&apos;s start (0 or 2 supported)\""),
            "{xml}"
        );
    }
}
