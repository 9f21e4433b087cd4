//! Bad scenes are refused with the JSON path, what was wrong, the unit and what is
//! allowed — and good ones (every bundled scene) load and build.

mod common;
use common::*;
use cutsim_sim::scene::{Scene, SceneError};

fn error_of(text: &str) -> SceneError {
    match Scene::from_json_str(text, "bad.json", None) {
        Err(e) => e,
        Ok(scene) => match cutsim_sim::build_tissue(&scene) {
            Err(e) => e,
            Ok(_) => panic!("scene was accepted"),
        },
    }
}

fn good() -> String {
    patch_scene([0.1, 0.08], [10, 9], 0.1, "")
}

#[test]
fn unknown_key_names_its_path_and_the_allowed_keys() {
    let e = error_of(&good().replace(r#""young_pa""#, r#""youngs_pa""#));
    assert_eq!(e.path, "model.msm.material.youngs_pa");
    assert!(e.message.contains("unknown field `youngs_pa`") && e.message.contains("`young_pa`"), "{e}");
    let e = error_of(&good().replace(r#""name": "test-patch","#, r#""name": "test-patch", "colour": "red","#));
    assert_eq!(e.path, "colour");
}

#[test]
fn negative_young_modulus_gives_unit_and_range() {
    let e = error_of(&good().replace(r#""young_pa": 100000"#, r#""young_pa": -5"#));
    assert_eq!(e.path, "model.msm.material.young_pa");
    assert!(e.message.starts_with("Young's modulus must be within [1, 10000000000] Pa, got -5"), "{e}");
    assert_eq!(e.to_string().split(": ").next(), Some("bad.json"));
}

#[test]
fn nan_is_explained() {
    let e = error_of(&good().replace(r#""thickness_m": 0.002"#, r#""thickness_m": NaN"#));
    assert_eq!(e.path, "model.msm.material.thickness_m");
    assert!(e.message.starts_with("NaN and Infinity are not numbers JSON allows"), "{e}");
}

#[test]
fn wrong_type_says_what_was_expected() {
    let e = error_of(&good().replace(r#""radius_m": 0.0005"#, r#""radius_m": "thin""#));
    assert_eq!(e.path, "tools[0].shape.cylinder.radius_m");
    assert!(e.message.contains("invalid type: string \"thin\", expected f64"), "{e}");
}

#[test]
fn empty_mesh_and_missing_file_are_refused() {
    let dir = std::env::temp_dir().join(format!("cutsim-bad-scenes-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("empty.obj"), "# nothing\nv 0 0 0\n").unwrap();
    let obj_scene = |path: &str| {
        good().replace(
            r#""geometry": { "patch": { "size_m": [0.1, 0.08], "resolution": [10, 9] } }"#,
            &format!(r#""geometry": {{ "obj": {{ "path": "{path}", "scale_m_per_unit": 0.001 }} }}"#),
        )
    };
    let load = |text: String| {
        let scene = Scene::from_json_str(&text, "bad.json", Some(&dir)).unwrap();
        cutsim_sim::build_tissue(&scene).err().expect("refused")
    };
    let e = load(obj_scene("empty.obj"));
    assert_eq!(e.path, "model.msm.geometry.obj");
    assert!(e.message.contains("the mesh is empty (0 vertices, 0 triangles)"), "{e}");
    let e = load(obj_scene("missing.obj"));
    assert_eq!(e.path, "model.msm.geometry.obj.path");
    assert!(e.message.contains("cannot open") && e.message.contains("missing.obj"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn explicit_step_above_the_stability_bound_is_refused_with_the_bound() {
    let e = error_of(&good().replace(r#""substeps": 12"#, r#""substeps": 1"#));
    assert_eq!(e.path, "model.msm.integrator.symplectic-euler.substeps");
    assert!(e.message.contains("is above the stability bound") && e.message.contains("use substeps ≥"), "{e}");
    // The suggested number of substeps is accepted.
    let needed: u32 = e.message.split("use substeps ≥ ").nth(1).unwrap().split(',').next().unwrap().trim().parse().unwrap();
    let ok = Scene::from_json_str(&good().replace(r#""substeps": 12"#, &format!(r#""substeps": {needed}"#)), "ok", None).unwrap();
    assert!(cutsim_sim::build_tissue(&ok).is_ok());
    assert!(cutsim_sim::build_tissue(&Scene::from_json_str(
        &good().replace(r#""substeps": 12"#, &format!(r#""substeps": {}"#, needed - 1)), "ok", None).unwrap()).is_err());
}

#[test]
fn cross_field_errors() {
    let e = error_of(&good().replace(r#""fixed": [ { "boundary": {} } ]"#, r#""fixed": [ { "box": { "min_m": [0, 0, 0], "max_m": [-1, 1, 1] } } ]"#));
    assert_eq!(e.path, "model.msm.fixed[0].box");
    let e = error_of(&good().replace(r#""fixed": [ { "boundary": {} } ]"#, r#""fixed": [ { "nodes": { "indices": [5, 99999] } } ]"#));
    assert_eq!(e.path, "model.msm.fixed[0].nodes.indices[1]");
    let e = error_of(&good().replace(r#""fixed": [ { "boundary": {} } ]"#, r#""fixed": [ { "boundary": { "axes": "xw" } } ]"#));
    assert_eq!(e.path, "model.msm.fixed[0].boundary.axes");
    let e = error_of(&good().replace(r#""resolution": [10, 9]"#, r#""resolution": [2000, 2000]"#));
    assert!(e.message.contains("at most 2000000 are allowed"), "{e}");
}

#[test]
fn every_bundled_scene_loads_and_builds() {
    let mut count = 0;
    for entry in std::fs::read_dir(scenes_dir()).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "json") {
            let scene = load_scene(&path);
            cutsim_sim::build_tissue(&scene).unwrap_or_else(|e| panic!("{e}"));
            count += 1;
        }
    }
    assert!(count >= 2);
}

#[test]
fn scene_schema_in_docs_is_the_generated_one() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/scene.schema.json");
    let generated = serde_json::to_string_pretty(&cutsim_sim::scene::json_schema()).unwrap() + "\n";
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "docs/scene.schema.json is out of date; regenerate it with\n  cargo run -p cutsim-server -- scene-schema > docs/scene.schema.json"
    );
}

/// A Cholesky factor at level 0 of a large box would take gigabytes: refused at load
/// from its symbolic size, with the size and what to use instead.
#[test]
fn a_cholesky_factor_too_large_is_refused_with_its_size() {
    let e = error_of(
        r#"{ "name": "big", "model": { "branched-grid": {
            "volume": { "box": { "size_m": [0.07, 0.07, 0.07], "voxel_size_m": 0.002 } },
            "materials": [ { "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 } ],
            "level": 0, "fixed": [ { "side": { "side": "-z" } } ],
            "solver": { "preconditioner": "cholesky" } } }, "tools": [] }"#,
    );
    let text = e.to_string();
    assert!(text.contains("model.branched-grid.solver.preconditioner"), "{text}");
    assert!(text.contains("Cholesky factor") && text.contains("MB") && text.contains("multigrid"), "{text}");
}
