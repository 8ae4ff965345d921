//! Bad input to the `diffluid` binary: each test writes a deliberately broken scene file
//! (the shipped `assets/scenes/dam_break.toml` with one thing changed) or passes a bad path
//! or option, runs `diffluid run <scene> --out <dir> --quiet`, and checks that the program
//! refuses it the way a user needs: a non-zero exit status, exactly one line on stderr that
//! starts with `error:` and names the problem (the key, and the line of the file where there
//! is one), no panic, and no output written. Every broken file is first checked to differ
//! from the valid one, so a test cannot silently run the valid scene; a positive control runs
//! the unmodified scene for two steps and checks that it succeeds and writes its outputs.

use crate::common::{asset, TempDir, EXE};
use std::path::Path;
use std::process::{Command, Output};

/// The valid scene every broken file is made from.
fn dam_break_text() -> String {
    let path = asset("scenes/dam_break.toml");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// The dam-break text with `from` (which must occur exactly once) replaced by `to`.
fn broken(from: &str, to: &str) -> String {
    let valid = dam_break_text();
    assert_eq!(
        valid.matches(from).count(),
        1,
        "{from:?} should occur exactly once in dam_break.toml; the test no longer matches the scene"
    );
    let text = valid.replacen(from, to, 1);
    assert_ne!(text, valid, "replacing {from:?} by {to:?} did not change the scene");
    text
}

/// The 1-based number of the one line of `text` whose trimmed content starts with `start`.
fn line_of(text: &str, start: &str) -> usize {
    let hits: Vec<usize> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| l.trim().starts_with(start))
        .map(|(n, _)| n + 1)
        .collect();
    assert_eq!(hits.len(), 1, "expected one line starting with {start:?}, found lines {hits:?}");
    hits[0]
}

/// Runs `diffluid run <scene> --out <out> --quiet <extra...>`.
fn run(scene: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(EXE)
        .arg("run")
        .arg(scene)
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(extra)
        .output()
        .expect("the diffluid binary starts")
}

/// Asserts the run failed cleanly with one `error:` line on stderr containing every one of
/// `needles`, and wrote nothing to `out`. Returns that line.
fn assert_refused(output: &Output, out: &Path, needles: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        !stderr.contains("panicked"),
        "the binary panicked instead of reporting an error:\n{stderr}"
    );
    assert!(
        !output.status.success(),
        "bad input was accepted (status {}); stdout: {stdout}; stderr: {stderr}",
        output.status
    );
    assert!(
        output.status.code().is_some(),
        "the binary was killed by a signal ({}); stderr: {stderr}",
        output.status
    );
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "stderr should be exactly one line, got {}:\n{stderr}", lines.len());
    let line = lines[0];
    assert!(line.starts_with("error:"), "stderr should start with \"error:\", got: {line}");
    for needle in needles {
        assert!(line.contains(needle), "stderr should mention {needle:?}, got: {line}");
    }
    assert!(!out.exists(), "a refused run should write nothing, but {} exists", out.display());
    line.to_string()
}

/// `line N:` as the error messages write it (with the colon, so `line 1` does not match
/// `line 12`).
fn at_line(n: usize) -> String {
    format!("line {n}:")
}

#[test]
fn missing_required_key_time_dt() {
    let dir = TempDir::new("missing_dt");
    let text = broken("dt = 0.05\n", "");
    // The [time] table is where the key is missing.
    let line = at_line(line_of(&text, "[time]"));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["missing field `dt`", &line]);
}

/// A table the file lacks altogether has no line: it was reported at `line 1: name`, or at
/// whatever line 1 held (a comment, here).
#[test]
fn missing_fluid_table() {
    let dir = TempDir::new("missing_fluid");
    let text = broken("[fluid]\ndensity = 1000.0\ngravity = [0.0, -9.81, 0.0]\n", "");
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    let line = assert_refused(&output, &dir.out(), &["the [fluid] table is missing"]);
    assert!(!line.contains("line 1"), "{line}");
}

#[test]
fn unknown_key_in_domain() {
    let dir = TempDir::new("unknown_key");
    let text = broken("dx = 0.1\n", "dx = 0.1\nfoo = 1\n");
    let line = at_line(line_of(&text, "foo = 1"));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["unknown field `foo`", &line]);
}

#[test]
fn zero_dx() {
    let dir = TempDir::new("zero_dx");
    let text = broken("dx = 0.1\n", "dx = 0.0\n");
    let line = at_line(line_of(&text, "dx ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["domain.dx", "positive", &line]);
}

#[test]
fn negative_dx() {
    let dir = TempDir::new("negative_dx");
    let text = broken("dx = 0.1\n", "dx = -0.1\n");
    let line = at_line(line_of(&text, "dx ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["domain.dx", "positive", "-0.1", &line]);
}

#[test]
fn zero_dt() {
    let dir = TempDir::new("zero_dt");
    let text = broken("dt = 0.05\n", "dt = 0.0\n");
    let line = at_line(line_of(&text, "dt ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["time.dt", "positive", &line]);
}

#[test]
fn negative_dt() {
    let dir = TempDir::new("negative_dt");
    let text = broken("dt = 0.05\n", "dt = -0.05\n");
    let line = at_line(line_of(&text, "dt ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["time.dt", "positive", "-0.05", &line]);
}

#[test]
fn liquid_region_outside_domain() {
    let dir = TempDir::new("liquid_outside");
    // The tank is 4 m long in x; the block now reaches 4.5 m.
    let text = broken("max = [4.0, 0.7, 1.5]", "max = [4.5, 0.7, 1.5]");
    // The error names `liquid[0]`, which is located at its [[liquid]] header.
    let line = at_line(line_of(&text, "[[liquid]]"));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["liquid[0]", "outside the domain", &line]);
}

#[test]
fn nan_in_gravity() {
    let dir = TempDir::new("nan_gravity");
    let text = broken("gravity = [0.0, -9.81, 0.0]", "gravity = [0.0, nan, 0.0]");
    let line = at_line(line_of(&text, "gravity ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["fluid.gravity", "finite", &line]);
}

#[test]
fn nan_in_liquid_box_corner() {
    let dir = TempDir::new("nan_liquid");
    let text = broken("min = [3.6, 0.0, 0.5]", "min = [nan, 0.0, 0.5]");
    let line = at_line(line_of(&text, "[[liquid]]"));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["liquid[0]", "finite", &line]);
}

#[test]
fn scene_file_does_not_exist() {
    let dir = TempDir::new("no_such_file");
    let path = dir.join("no_such_scene.toml");
    assert!(!path.exists());
    let output = run(&path, &dir.out(), &[]);
    let shown = path.display().to_string();
    assert_refused(&output, &dir.out(), &["cannot read scene file", &shown]);
}

#[test]
fn scene_path_is_a_directory() {
    let dir = TempDir::new("directory");
    let path = dir.join("scenes.toml");
    std::fs::create_dir(&path).unwrap();
    let output = run(&path, &dir.out(), &[]);
    let shown = path.display().to_string();
    assert_refused(&output, &dir.out(), &["cannot read scene file", &shown]);
}

#[test]
fn malformed_toml_syntax() {
    let dir = TempDir::new("malformed");
    // An unclosed table header.
    let text = broken("[time]\n", "[time\n");
    let line = at_line(line_of(&text, "[time"));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["unclosed table", &line]);
}

#[test]
fn zero_steps_option() {
    let dir = TempDir::new("steps_zero");
    let scene = dir.scene(&dam_break_text());
    let output = run(&scene, &dir.out(), &["--steps", "0"]);
    assert_refused(&output, &dir.out(), &["--steps", "at least 1"]);
}

#[test]
fn particles_per_cell_not_a_cube() {
    let dir = TempDir::new("ppc5");
    let text = broken("particles_per_cell = 8\n", "particles_per_cell = 5\n");
    let line = at_line(line_of(&text, "particles_per_cell ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["solver.particles_per_cell", "got 5", &line]);
}

/// 254 extrapolation layers overflowed the layer counter and tripped an assertion in the
/// first step (a panic from a scene file); now the setting is checked with the others.
#[test]
fn too_many_extrapolation_layers() {
    let dir = TempDir::new("layers");
    let text = broken("extrapolation_layers = 3\n", "extrapolation_layers = 254\n");
    let line = at_line(line_of(&text, "extrapolation_layers ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["solver.extrapolation_layers", "got 254", &line]);
}

/// The density projection's tolerance is checked like the pressure's: zero would ask CG for
/// an exact answer it cannot give.
#[test]
fn zero_density_tolerance() {
    let dir = TempDir::new("density_tolerance");
    let text =
        broken("extrapolation_layers = 3\n", "extrapolation_layers = 3\ndensity_tolerance = 0.0\n");
    let line = at_line(line_of(&text, "density_tolerance ="));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["solver.density_tolerance", "got 0", &line]);
}

/// The density projection's gain is refused outside (0, 2], its passes outside 1 to 4 and its
/// face ramp outside [0, 1), naming the key and the line: a gain or passes of zero would turn the projection off
/// without saying so, and above a gain of 2 the displacement overshoots (the surge lost 7%
/// of its volume at 2.5).
#[test]
fn density_settings_out_of_range() {
    for (key, value, shown) in [
        ("density_gain", "0.0", "got 0"),
        ("density_gain", "2.5", "got 2.5"),
        ("density_gain", "nan", "got NaN"),
        ("density_passes", "0", "got 0"),
        ("density_passes", "5", "got 5"),
        ("density_face_ramp", "1.0", "got 1"),
        ("density_face_ramp", "-0.1", "got -0.1"),
    ] {
        let dir = TempDir::new(key);
        let text = broken(
            "extrapolation_layers = 3\n",
            &format!("extrapolation_layers = 3\n{key} = {value}\n"),
        );
        let line = at_line(line_of(&text, &format!("{key} =")));
        let output = run(&dir.scene(&text), &dir.out(), &[]);
        assert_refused(&output, &dir.out(), &[&format!("solver.{key}"), shown, &line]);
    }
}

/// A 880 × 330 × 440 tank (128M cells, just under the 512³ cap) needs some 32 GB for its grid
/// alone: refused before anything is allocated with the estimate and what is available (it
/// used to abort on a failed allocation, or take the machine's memory until the OS killed
/// it). The grid's share is what tips it: at 96M cells (24 GB) the estimate sat a few
/// hundred MB from this 24 GiB machine's free memory, and the narrow band's smaller particle
/// count let it through to run.
#[test]
fn a_grid_too_large_for_the_machine_is_refused() {
    let dir = TempDir::new("huge");
    let text = broken("dx = 0.1\n", &format!("dx = {:?}\n", 1.0 / 220.0));
    let output = run(&dir.scene(&text), &dir.out(), &[]);
    assert_refused(&output, &dir.out(), &["needs about", "GB", "solver.memory_limit_gb"]);
}

/// Positive control: the unmodified scene runs, so the failures above are due to the edits.
#[test]
fn valid_scene_runs_and_writes_outputs() {
    let dir = TempDir::new("valid");
    let scene = dir.scene(&dam_break_text());
    let output = run(&scene, &dir.out(), &["--steps", "2"]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "the valid scene failed ({}): {stderr}", output.status);
    assert!(
        stderr.trim().is_empty(),
        "a quiet successful run should print nothing on stderr: {stderr}"
    );
    let summary = dir.out().join("summary.json");
    assert!(summary.is_file(), "{} was not written", summary.display());
    let ply = dir.out().join("particles").join("0000.ply");
    assert!(ply.is_file(), "{} was not written", ply.display());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    assert_eq!(json["steps"].as_array().map(Vec::len), Some(2), "summary.json: {json}");
}
