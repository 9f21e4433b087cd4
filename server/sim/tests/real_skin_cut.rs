//! A cut across the real CT skin patch (../shared/data, units mm): the mesh stays
//! manifold with two separate lips, every created triangle keeps the minimum angle, and
//! mass is conserved up to the removed region.

mod common;
use common::*;
use cutsim_sim::math::Vec3;
use cutsim_sim::msm::cut::node_matching::MIN_ANGLE_DEG;
use cutsim_sim::tissue::Tissue;

#[test]
fn cut_across_real_skin_is_manifold_with_two_lips_and_conserves_mass() {
    let mut m = build(&load_scene(&scenes_dir().join("skin-real.json")));
    assert_eq!(m.node_count(), 1496);
    let mass_before = m.total_mass();
    assert!((mass_before - m.mass_of_triangles()).abs() < 1e-12 * mass_before);

    // A 6 cm incision across the anterior abdomen, the blade along the skin's normal (+y).
    straight_cut(&mut m, Vec3::new(-0.03, 0.0, 0.02), Vec3::new(0.03, 0.0, -0.01), Vec3::y(), 0.02, 120);
    step_with(&mut m, None, false, 500);
    let c = m.counters();
    assert_eq!((c.cuts, c.reconstruction_fallbacks), (1, 0), "{:?}", m.last_fallback_reason());
    assert!(c.incision_length_m > 0.055 && c.incision_length_m < 0.075, "incision {} m", c.incision_length_m);

    // Manifold and consistently oriented.
    live_mesh(&m).check().unwrap_or_else(|e| panic!("not manifold: {e}"));
    assert_eq!(m.piece_count(), 1);

    // Two separate lips: they share only their closed ends, every lip edge is a border
    // edge (one triangle), and the wound has opened between them.
    let incision = &m.incisions()[0];
    let [left, right] = &incision.lips;
    assert!(left.len() >= 10 && right.len() >= 10, "lips of {} and {} vertices", left.len(), right.len());
    let shared: Vec<u32> = left.iter().filter(|v| right.contains(v)).copied().collect();
    assert_eq!(shared, vec![left[0], *left.last().unwrap()], "lips meet only at the two ends");
    let triangles: Vec<[u32; 3]> = m.triangles().map(|(_, t)| t).collect();
    for lip in [left, right] {
        for w in lip.windows(2) {
            let users = triangles.iter().filter(|t| t.contains(&w[0]) && t.contains(&w[1])).count();
            assert_eq!(users, 1, "lip edge {}–{} is a border edge", w[0], w[1]);
        }
    }
    let mid = left.len() / 2;
    let gap = (m.positions()[left[mid] as usize] - m.positions()[right[mid] as usize]).norm();
    assert!(gap > 1e-3, "the wound opened: {:.2} mm", gap * 1e3);

    // Minimum angle of every triangle the cut created, at creation.
    let angle = m.min_cut_angle_deg().unwrap();
    assert!(angle >= MIN_ANGLE_DEG, "created triangle with {angle:.2}°");

    // Mass: what remains is exactly ρ·t·(remaining + new area), less than before, and no
    // more was lost than the swept strip (incision length × (2·sweep radius + 2 edges)).
    let mass_after = m.total_mass();
    assert!((mass_after - m.mass_of_triangles()).abs() < 1e-12 * mass_after, "bookkeeping");
    assert!(mass_after < mass_before);
    let material = m.material();
    let strip_area = c.incision_length_m * 2.0 * (0.5 * m.mean_edge_length_m() + 2.0 * m.mean_edge_length_m());
    let max_loss = material.density_kg_per_m3 * material.thickness_m * strip_area;
    assert!(mass_before - mass_after < max_loss, "lost {:e} kg, at most {max_loss:e}", mass_before - mass_after);
    println!(
        "real skin: incision {:.1} mm, gap {:.2} mm, min new angle {angle:.1}°, mass {:.4} g → {:.4} g",
        c.incision_length_m * 1e3,
        gap * 1e3,
        mass_before * 1e3,
        mass_after * 1e3
    );
}
