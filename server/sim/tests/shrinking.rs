//! The shrinking effect (paper Section 2.1, Fig. 6): after a cut, the gap between two
//! points facing each other on the two lips rises quickly, overshoots, falls back and
//! settles; the plateau grows with the residual strain εr and vanishes at εr = 0.

mod common;
use common::*;
use cutsim_sim::math::Vec3;

/// Gap (m) between the middle lip vertices, sampled every step for `steps` steps from
/// the moment they are made: a 4 cm cut in one stroke update (blade in at one end,
/// across in one step, then out), so that every lip vertex is born at the same time.
fn gap_curve(residual_strain: f64, steps: usize) -> Vec<f64> {
    let mut m = build(&scene(&patch_scene([0.1, 0.08], [40, 37], residual_strain, "")));
    let (from, to) = (Vec3::new(-0.02, 0.0, 0.0), Vec3::new(0.02, 0.0, 0.0));
    step_with(&mut m, Some(pose(from - Vec3::z() * 0.005, Vec3::z())), true, 1);
    step_with(&mut m, Some(pose(to - Vec3::z() * 0.005, Vec3::z())), true, 1);
    assert_eq!(cutsim_sim::tissue::Tissue::counters(&m).cut_updates, 1, "the whole incision in one update");
    let incision = m.incisions()[0].clone();
    // The two lips' vertices at the middle of the incision: copies of one curve point.
    let mid = incision.lips[0].len() / 2;
    let (a, b) = (incision.lips[0][mid] as usize, incision.lips[1][mid] as usize);
    assert_ne!(a, b, "lips are split");
    let mut curve = vec![(m.positions()[a] - m.positions()[b]).norm()];
    for _ in 1..steps {
        step_with(&mut m, None, false, 1);
        curve.push((m.positions()[a] - m.positions()[b]).norm());
    }
    curve
}

#[test]
fn gap_rises_overshoots_falls_back_and_settles() {
    let d = gap_curve(0.1, 1500);
    let (peak_at, peak) = d.iter().copied().enumerate().fold((0, 0.0), |best, (i, v)| if v > best.1 { (i, v) } else { best });
    let plateau = d[d.len() - 100..].iter().sum::<f64>() / 100.0;
    println!("εr = 0.1: gap at the cut {:.3} mm, at 1 ms {:.3} mm, peak {:.3} mm at {} ms, plateau {:.3} mm", d[0] * 1e3, d[1] * 1e3, peak * 1e3, peak_at, plateau * 1e3);
    // Rise: the lips start together and the gap grows to the peak.
    assert!(d[0] < 1e-9, "the lips start together: {:.3} mm", d[0] * 1e3);
    assert!(d[1] < peak, "rises");
    assert!(peak_at > 1 && peak_at < 300, "peaks early, at {peak_at} ms");
    // Overshoot and fall back: the plateau is clearly below the peak.
    assert!(plateau < 0.97 * peak, "falls back: plateau {:.3} mm vs peak {:.3} mm", plateau * 1e3, peak * 1e3);
    // Settles: the last 300 ms vary by under 1 % of the plateau.
    let tail = &d[d.len() - 300..];
    let spread = tail.iter().fold(f64::MIN, |a, &b| a.max(b)) - tail.iter().fold(f64::MAX, |a, &b| a.min(b));
    assert!(spread < 0.01 * plateau, "settles: last 300 ms vary by {:.4} mm", spread * 1e3);
    assert!(plateau > 1e-3, "the wound stays open: plateau {:.3} mm", plateau * 1e3);
}

#[test]
fn plateau_grows_with_residual_strain_and_vanishes_without_it() {
    let plateau = |eps: f64| {
        let d = gap_curve(eps, 1200);
        d[d.len() - 100..].iter().sum::<f64>() / 100.0
    };
    let values: Vec<(f64, f64)> = [0.0, 0.05, 0.1, 0.2].into_iter().map(|e| (e, plateau(e))).collect();
    for (e, p) in &values {
        println!("εr = {e}: plateau gap {:.3} mm", p * 1e3);
    }
    assert!(values[0].1 < 1e-5, "no residual stress, no gaping: {:.4} mm", values[0].1 * 1e3);
    for w in values.windows(2) {
        assert!(w[1].1 > w[0].1 * 1.2, "plateau grows with εr: {:?}", values);
    }
}
