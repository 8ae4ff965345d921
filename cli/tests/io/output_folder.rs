//! What `diffluid run` writes stays in its output folder, holds one run, whole:
//!
//! - names cannot escape it: a scene `name` or a body name with `..`, `/`, an absolute path,
//!   XML markup or a NUL is refused when the scene is read (it made `summary.json` land two
//!   folders up and PLY frames at an absolute path), and so are two bodies of one name (their
//!   frames overwrote each other);
//! - Ctrl-C stops the run after the step in progress and keeps `summary.json` and
//!   `bodies.csv` of every finished step (they were written only at the end);
//! - a second run into the folder clears what the first wrote (a 3-step run into the folder
//!   of a 5-step one left frames 4 and 5, and `render` drew them), a folder holding other
//!   files is refused without `--force`, and a folder another run holds is refused;
//! - `render` draws at most 4096 pixels a side and a failed `render` leaves the picture that
//!   was there.
//!
//! Each test runs the binary in a folder of its own, on a small tank (a few ms a step).

use crate::common::EXE;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A 0.8 × 0.6 × 0.6 m tank at dx 0.1 with a pool and a ball named `ball`; `name` and
/// `extra` (more keys or tables) edit it.
fn scene(name: &str, ball: &str, extra: &str) -> String {
    format!(
        r#"name = {name}
[domain]
size = [0.8, 0.6, 0.6]
dx = 0.1
[time]
dt = 0.01
steps = 3
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [0.8, 0.3, 0.6] }}
[[body]]
name = {ball}
shape = {{ kind = "ball", radius = 0.1 }}
density = 500.0
position = [0.4, 0.45, 0.3]
{extra}"#
    )
}

/// A fresh folder for one test, removed when dropped.
struct Sandbox(PathBuf);

impl Sandbox {
    fn new(test: &str) -> Sandbox {
        let dir = std::env::temp_dir()
            .join(format!("diffluid-output-folder-{}-{test}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        std::fs::create_dir_all(dir.join("work")).unwrap();
        Sandbox(dir)
    }

    /// Writes the scene text into `work/scene.toml`.
    fn scene(&self, text: &str) -> PathBuf {
        let p = self.0.join("work").join("scene.toml");
        std::fs::write(&p, text).unwrap();
        p
    }

    /// Every file under the sandbox, relative to it.
    fn files(&self) -> Vec<PathBuf> {
        fn walk(dir: &Path, base: &Path, out: &mut Vec<PathBuf>) {
            for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, base, out);
                } else {
                    out.push(p.strip_prefix(base).unwrap().to_path_buf());
                }
            }
        }
        let mut out = Vec::new();
        walk(&self.0, &self.0, &mut out);
        out.sort();
        out
    }
}

impl Drop for Sandbox {
    fn drop(&mut self) {
        std::fs::remove_dir_all(&self.0).ok();
    }
}

/// `diffluid <args>` run in the sandbox's `work/` folder.
fn diffluid(sandbox: &Sandbox, args: &[&str]) -> Output {
    Command::new(EXE)
        .current_dir(sandbox.0.join("work"))
        .args(args)
        .output()
        .expect("the diffluid binary starts")
}

/// The one `error:` line of a failed command.
fn error_line(output: &Output) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(!output.status.success(), "accepted; stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line expected: {stderr}");
    assert!(lines[0].starts_with("error: "), "{stderr}");
    lines[0].to_string()
}

/// A TOML basic string holding `s`.
fn toml_str(s: &str) -> String {
    let mut out = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => out.push_str(&format!("\\u{:04X}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[test]
fn names_that_would_leave_the_folder_are_refused_when_the_scene_is_read() {
    let sandbox = Sandbox::new("names");
    let abs = sandbox.0.join("abs").join("x");
    let abs = abs.to_str().unwrap();
    // (scene name, ball name, the key the error names).
    let cases = [
        ("../../x", "ball", "name"),
        ("a/b", "ball", "name"),
        ("", "ball", "name"),
        ("ok", "../../../x", "body[0].name"),
        ("ok", abs, "body[0].name"),
        ("ok", "a/b", "body[0].name"),
        ("ok", "a&b", "body[0].name"),
        ("ok", "a<b", "body[0].name"),
        ("ok", "nul\u{0}x", "body[0].name"),
        ("ok", "..", "body[0].name"),
        ("ok", ".hidden", "body[0].name"),
    ];
    for (name, ball, key) in cases {
        let path = sandbox.scene(&scene(&toml_str(name), &toml_str(ball), ""));
        // Without --out the folder is out/<name>; with it, the bodies' frames and VTK
        // series still go by the body's name.
        let without = diffluid(&sandbox, &["run", path.to_str().unwrap(), "--quiet", "--vtk"]);
        let line = error_line(&without);
        assert!(line.contains(&format!("{key}:")), "{name:?}/{ball:?}: {line}");
        let with = diffluid(
            &sandbox,
            &["run", path.to_str().unwrap(), "--quiet", "--vtk", "--out", "deep/a/b/out"],
        );
        error_line(&with);
        assert_eq!(sandbox.files(), [PathBuf::from("work/scene.toml")], "{name:?}/{ball:?}");
    }
    // The rule lets every shipped kind of name through.
    let path = sandbox.scene(&scene("\"dam_break-2.v1\"", "\"bällchen_1\"", ""));
    let ok = diffluid(&sandbox, &["run", path.to_str().unwrap(), "--quiet", "--vtk"]);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let out = sandbox.0.join("work/out/dam_break-2.v1");
    assert!(out.join("bodies/bällchen_1_0003.ply").is_file());
    let pvd = std::fs::read_to_string(out.join("vtk/body_bällchen_1.pvd")).unwrap();
    assert!(pvd.contains("file=\"body_bällchen_1_0003.vtp\""), "{pvd}");
}

#[test]
fn two_bodies_of_one_name_are_refused() {
    let sandbox = Sandbox::new("duplicates");
    let second = "[[body]]\nname = \"ball\"\nshape = { kind = \"ball\", radius = 0.05 }\n\
                  density = 500.0\nposition = [0.15, 0.45, 0.15]\n";
    let text = scene("\"two\"", "\"ball\"", second);
    let path = sandbox.scene(&text);
    let line = error_line(&diffluid(&sandbox, &["run", path.to_str().unwrap(), "--quiet"]));
    // The second body's name, at its line.
    let at = text.lines().enumerate().filter(|(_, l)| l.starts_with("name = \"ball\"")).nth(1);
    let at = at.unwrap().0 + 1;
    assert!(line.contains(&format!("line {at}: body[1].name")), "{line}");
    assert!(line.contains("body[0]"), "{line}");
    // An unnamed body takes the name body<i>: the same as a body named so.
    let unnamed = second.replace("name = \"ball\"\n", "");
    let path = sandbox.scene(&scene("\"two\"", "\"body1\"", &unnamed));
    let line = error_line(&diffluid(&sandbox, &["run", path.to_str().unwrap(), "--quiet"]));
    assert!(line.contains("body[1].name") && line.contains("\"body1\""), "{line}");
    assert_eq!(sandbox.files(), [PathBuf::from("work/scene.toml")]);
}

/// A world built in code may name its bodies as it likes (handles are its keys), but the
/// recorder writes files by name: it refuses names that would leave the folder or collide.
#[test]
fn the_recorder_refuses_names_a_scene_file_could_not_give() {
    use diffluid::geometry::body::RigidBody;
    use diffluid::io::recorder::{Frames, RunFolder, RunRecorder};
    use diffluid::math::{Pose, SharedShape, Vec3};
    let sandbox = Sandbox::new("recorder");
    let ball = |name: &str, x: f64| {
        let pose = Pose::from_translation(Vec3::new(x, 0.45, 0.3));
        RigidBody::with_density(name.into(), SharedShape::ball(0.08), pose, 500.0)
    };
    let frames = Frames { every: 1, particles: false, vtk: true, surface: None };
    for bodies in [vec![ball("../escape", 0.3)], vec![ball("b", 0.2), ball("b", 0.6)]] {
        let mut builder = diffluid::world::Simulation::builder([0.8, 0.6, 0.6], 0.1);
        for b in bodies {
            builder = builder.body(b);
        }
        let sim = builder.build().unwrap();
        let out = sandbox.0.join("work").join("out");
        let folder = RunFolder::claim(&out, false).unwrap();
        let err = RunRecorder::new(folder, "coded", frames, &sim).err().expect("refused");
        assert!(err.to_string().contains("body name"), "{err}");
        let files = sandbox.files();
        assert!(
            files.iter().all(|f| f.starts_with("work/out")),
            "written outside the folder: {files:?}"
        );
    }
}

/// Ctrl-C (SIGINT) stops the run after the step in progress: the summary and the body rows
/// of every finished step are there, as many as the particle frames, and the exit status
/// is 130.
#[cfg(unix)]
#[test]
fn ctrl_c_keeps_the_summary_and_the_rows_of_every_finished_step() {
    let sandbox = Sandbox::new("sigint");
    let path = sandbox.scene(&scene("\"long\"", "\"ball\"", ""));
    let mut child = Command::new(EXE)
        .current_dir(sandbox.0.join("work"))
        .args(["run", path.to_str().unwrap(), "--quiet", "--steps", "100000", "--out", "o"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let frame = sandbox.0.join("work/o/particles/0005.ply");
    // Not a timing: the wait ends when the frame is there (or the run ended on its own).
    while !frame.exists() && child.try_wait().unwrap().is_none() {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let sent = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(sent.success());
    let output = child.wait_with_output().unwrap();
    assert_eq!(output.status.code(), Some(130), "{}", String::from_utf8_lossy(&output.stderr));
    let line = error_line(&output);
    assert!(line.contains("interrupted after step"), "{line}");
    let out = sandbox.0.join("work/o");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let steps = summary["steps"].as_array().unwrap().len();
    assert!(steps >= 5, "{steps} steps in the summary");
    assert_eq!(summary["status"], "stopped");
    assert!(summary["stopped"].as_str().unwrap().contains("interrupted"));
    let rows = std::fs::read_to_string(out.join("bodies.csv")).unwrap();
    assert_eq!(rows.lines().count(), 1 + (steps + 1), "a header and rows for steps 0..={steps}");
    assert!(rows.lines().last().unwrap().starts_with(&format!("{steps},")));
    let frames = std::fs::read_dir(out.join("particles")).unwrap().count();
    assert_eq!(frames, steps + 1, "frames 0..={steps}");
}

#[test]
fn a_second_run_clears_the_first_and_a_busy_or_foreign_folder_is_refused() {
    let sandbox = Sandbox::new("rerun");
    let path = sandbox.scene(&scene("\"rerun\"", "\"ball\"", ""));
    let path = path.to_str().unwrap();
    let run = |steps: &str, extra: &[&str]| {
        let mut args = vec!["run", path, "--quiet", "--out", "o", "--steps", steps, "--vtk"];
        args.extend_from_slice(extra);
        diffluid(&sandbox, &args)
    };
    assert!(run("5", &[]).status.success());
    assert!(run("3", &[]).status.success());
    let out = sandbox.0.join("work/o");
    let count = |sub: &str| std::fs::read_dir(out.join(sub)).unwrap().count();
    assert_eq!(count("particles"), 4, "frames 0..=3 only");
    assert_eq!(count("bodies"), 4);
    // 4 frames of the liquid, the grid and the ball, and their 3 collections.
    assert_eq!(count("vtk"), 3 * 4 + 3);
    let pvd = std::fs::read_to_string(out.join("vtk/liquid.pvd")).unwrap();
    assert!(!pvd.contains("0004"), "{pvd}");
    // A file the run does not write: refused, then kept with --force.
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let line = error_line(&run("2", &[]));
    assert!(line.contains("notes.txt") && line.contains("--force"), "{line}");
    assert_eq!(count("particles"), 4, "a refused run clears nothing");
    assert!(run("2", &["--force"]).status.success());
    assert_eq!(std::fs::read_to_string(out.join("notes.txt")).unwrap(), "mine");
    assert_eq!(count("particles"), 3);
    // A folder another run holds.
    let held = diffluid::io::recorder::RunFolder::lock(&out).unwrap();
    let line = error_line(&run("2", &["--force"]));
    assert!(line.contains("another diffluid"), "{line}");
    drop(held);
    assert!(run("2", &["--force"]).status.success());
}

#[test]
fn render_is_bounded_and_a_failed_render_keeps_the_picture() {
    let sandbox = Sandbox::new("render");
    let path = sandbox.scene(&scene("\"pictures\"", "\"ball\"", ""));
    let ran = diffluid(&sandbox, &["run", path.to_str().unwrap(), "--quiet", "--surface"]);
    assert!(ran.status.success(), "{}", String::from_utf8_lossy(&ran.stderr));
    let dir = "out/pictures";
    let gif = sandbox.0.join("work").join(dir).join("render.gif");
    assert!(diffluid(&sandbox, &["render", dir, "--width", "200"]).status.success());
    let drawn = std::fs::read(&gif).unwrap();
    assert!(drawn.starts_with(b"GIF8"));
    for (args, needle) in [
        (vec!["--width", "5000"], "width: must be 64 to 4096 pixels, got 5000"),
        (vec!["--width", "100000"], "got 100000"),
        (vec!["--width", "10"], "got 10"),
        (vec!["--frame", "1", "--out", "out/pictures/render.gif"], "path ending in .png"),
    ] {
        let mut all = vec!["render", dir];
        all.extend(args);
        let line = error_line(&diffluid(&sandbox, &all));
        assert!(line.contains(needle), "{line}");
        assert_eq!(std::fs::read(&gif).unwrap(), drawn, "render.gif was replaced");
    }
}
