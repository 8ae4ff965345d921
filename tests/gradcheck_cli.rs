//! `diffluid gradcheck assets/scenes/gradcheck_box.toml --json` checks the adjoint gradient
//! of every initial body parameter against central differences of the same forward map
//! (surface held fixed), and reports the paper's approximation beside it. Every full
//! rel_error must be at most 1e-3 (the command itself fails otherwise).

use std::process::Command;

#[test]
fn gradcheck_box_json_has_every_rel_error_below_1e_3() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/scenes/gradcheck_box.toml");
    let out = Command::new(env!("CARGO_BIN_EXE_diffluid"))
        .args(["gradcheck", scene, "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let params = v["params"].as_array().unwrap();
    assert_eq!(params.len(), 12, "v, ω, x, q of the box");
    for p in params {
        let rel = p["rel_error"].as_f64().unwrap();
        assert!(rel <= 1e-3, "{}: rel_error {rel}", p["name"]);
        assert!(
            p["adjoint"].as_f64().unwrap().is_finite() && p["fd"].as_f64().unwrap().is_finite()
        );
    }
    // The paper's approximation drops the pose dependence of the geometry: it must be
    // measurably worse somewhere, or the comparison means nothing.
    let worst_paper = v["paper"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["rel_error"].as_f64().unwrap())
        .fold(0.0, f64::max);
    assert!(worst_paper > 1e-2, "paper approximation unexpectedly exact: {worst_paper}");
}
