//! The shrinking effect (paper Section 2.1, Fig. 6): after a cut, the gap between two
//! points facing each other on the two lips rises quickly, overshoots, falls back and
//! settles; the plateau grows with the residual strain εr and vanishes at εr = 0.

use cutsim_sim::accuracy::membrane::{peak_and_plateau, shrinking_gap_curve};

fn gap_curve(residual_strain: f64, steps: usize) -> Vec<f64> {
    shrinking_gap_curve(residual_strain, steps).unwrap()
}

#[test]
fn gap_rises_overshoots_falls_back_and_settles() {
    let d = gap_curve(0.1, 1500);
    let ((peak_at, peak), plateau) = peak_and_plateau(&d);
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
    let plateau = |eps: f64| peak_and_plateau(&gap_curve(eps, 1200)).1;
    let values: Vec<(f64, f64)> = [0.0, 0.05, 0.1, 0.2].into_iter().map(|e| (e, plateau(e))).collect();
    for (e, p) in &values {
        println!("εr = {e}: plateau gap {:.3} mm", p * 1e3);
    }
    assert!(values[0].1 < 1e-5, "no residual stress, no gaping: {:.4} mm", values[0].1 * 1e3);
    for w in values.windows(2) {
        assert!(w[1].1 > w[0].1 * 1.2, "plateau grows with εr: {:?}", values);
    }
}
