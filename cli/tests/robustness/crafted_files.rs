//! Crafted files: what the `diffluid` binary reads back (an optimisation's `checkpoint.json`,
//! a run's `summary.json` and surface and body PLY frames) and the files a scene names (the
//! scene itself, its OBJ meshes) may be anything a user or an attacker puts there: valid JSON
//! with the wrong contents, a header that promises 2⁶² vertices, a FIFO that never delivers,
//! `/dev/zero` that never ends. Each must end with one `error:` line naming the file and exit
//! status 1: never a panic (exit 101), an abort on an allocation, a read until memory runs
//! out, or a wait for ever.
//!
//! Every command runs under a watchdog (a process still running after a minute is a hang,
//! killed and reported) and a 4 GB address-space limit (`ulimit -v`), so a test of an
//! unbounded read fails instead of taking the machine's memory. Neither is a timing
//! assertion: the valid cases finish in about a second.

use crate::common::{builtin_text, TempDir, EXE};
use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// How a command ended: its exit code (None: killed by a signal) and its stderr.
struct Ended {
    code: Option<i32>,
    stderr: String,
}

/// Runs the binary with `args` under the watchdog and the memory limit.
fn diffluid(args: &[&str]) -> Ended {
    let mut child = Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 4000000; exec \"$@\"")
        .arg("sh")
        .arg(EXE)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the diffluid binary starts");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(60) {
            child.kill().ok();
            child.wait().ok();
            panic!("diffluid {args:?} still ran after a minute: it hangs");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stderr = String::new();
    child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
    Ended { code: status.code(), stderr }
}

/// Asserts one `error:` line containing every needle and exit status 1.
fn assert_refused(ended: &Ended, needles: &[&str]) -> String {
    let stderr = &ended.stderr;
    assert!(!stderr.contains("panicked"), "a panic instead of an error:\n{stderr}");
    assert!(!stderr.contains("memory allocation"), "an abort on an allocation:\n{stderr}");
    assert_eq!(ended.code, Some(1), "exit status {:?}, stderr:\n{stderr}", ended.code);
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "stderr should be one line:\n{stderr}");
    assert!(lines[0].starts_with("error:"), "{}", lines[0]);
    for needle in needles {
        assert!(lines[0].contains(needle), "stderr should mention {needle:?}: {}", lines[0]);
    }
    lines[0].to_string()
}

fn mkfifo(path: &Path) {
    let ok = Command::new("mkfifo").arg(path).status().expect("mkfifo runs").success();
    assert!(ok, "mkfifo {}", path.display());
}

// ---------------------------------------------------------------------------------------
// Checkpoints

/// The recovery scene with `optimizer` and 4 steps (an epoch takes a few milliseconds).
fn recover_scene(optimizer: &str) -> String {
    let base = builtin_text("recover_box");
    let text = base
        .replacen("optimizer = { kind = \"gd\", learning_rate = 5.0 }", optimizer, 1)
        .replacen("steps = 20", "steps = 4", 1);
    assert!(text.contains(optimizer) && text.contains("steps = 4"));
    text
}

/// `diffluid optimize DIR/scene.toml --quiet --out DIR/out` with `extra`.
fn optimize(dir: &Path, extra: &[&str]) -> Ended {
    let (scene, out) = (dir.join("scene.toml"), dir.join("out"));
    let mut args = vec!["optimize", scene.to_str().unwrap(), "--quiet", "--out"];
    args.push(out.to_str().unwrap());
    args.extend_from_slice(extra);
    diffluid(&args)
}

/// A folder holding `scene.toml` for `optimizer` and the checkpoint of a 3-epoch run of it.
fn checkpointed(test: &str, optimizer: &str) -> (TempDir, serde_json::Value) {
    let dir = TempDir::new(test);
    std::fs::write(dir.join("scene.toml"), recover_scene(optimizer)).unwrap();
    let ended = optimize(&dir, &["--epochs", "3"]);
    assert_eq!(ended.code, Some(0), "{}", ended.stderr);
    let text = std::fs::read_to_string(dir.join("out/checkpoint.json")).unwrap();
    let ck: serde_json::Value = serde_json::from_str(&text).unwrap();
    (dir, ck)
}

/// Resumes the scene of `dir` from `checkpoint` (written over the run's) and asserts it is
/// refused naming the checkpoint, with every needle, and no word of a scene file.
fn resume_refused(dir: &Path, checkpoint: &serde_json::Value, needles: &[&str]) -> String {
    let path = dir.join("out/checkpoint.json");
    std::fs::write(&path, serde_json::to_string_pretty(checkpoint).unwrap()).unwrap();
    let ended = optimize(dir, &["--resume"]);
    let shown = path.display().to_string();
    let mut all = vec!["checkpoint", shown.as_str()];
    all.extend_from_slice(needles);
    let line = assert_refused(&ended, &all);
    assert!(!line.contains("scene file"), "{line}");
    line
}

/// An Adam run resumed from checkpoints of the right form but the wrong contents: gradient
/// descent's state (with and without the `settings` of newer checkpoints: the check of the
/// settings used to be all there was, and an older file has none), moments of the wrong
/// length, a step count or a `next_epoch` that does not match the history, epochs out of
/// order, parameters that are not finite or not the scene's where they are not optimised.
/// Each used to panic (`unreachable!`, an index out of bounds) or go on with a wrong state.
#[test]
fn adam_checkpoints_with_the_wrong_contents_are_refused() {
    let (dir, ck) = checkpointed("adam", "optimizer = { kind = \"adam\", learning_rate = 0.1 }");
    assert_eq!(ck["next_epoch"], 3);

    let mut gd = ck.clone();
    gd["optimizer"] = "Gd".into();
    resume_refused(&dir, &gd, &["gradient descent", "Adam"]);
    let mut older = gd.clone();
    older.as_object_mut().unwrap().remove("settings");
    resume_refused(&dir, &older, &["gradient descent", "Adam"]);

    let mut empty_m = ck.clone();
    empty_m["optimizer"]["Adam"]["m"] = serde_json::json!([]);
    resume_refused(&dir, &empty_m, &["optimizer.Adam.m", "3"]);

    let mut t = ck.clone();
    t["optimizer"]["Adam"]["t"] = 7.into();
    resume_refused(&dir, &t, &["optimizer.Adam.t"]);

    let mut ahead = ck.clone();
    ahead["next_epoch"] = 5.into();
    resume_refused(&dir, &ahead, &["next_epoch", "history"]);

    let mut shuffled = ck.clone();
    shuffled["history"][1]["epoch"] = 2.into();
    resume_refused(&dir, &shuffled, &["history[1].epoch"]);

    let mut moved = ck.clone();
    moved["params"]["x"] = serde_json::json!([0.1, 0.2, 0.3]);
    resume_refused(&dir, &moved, &["params.x", "not optimised"]);

    let mut huge = ck.clone();
    huge["params"]["v"] = serde_json::json!([1e308, 1e308, 1e308]);
    huge["params"]["q"] = serde_json::json!([0.0, 0.0, 0.0, 0.0]);
    resume_refused(&dir, &huge, &["params.q"]);

    let mut other = ck.clone();
    other["scene"] = "dam_break".into();
    resume_refused(&dir, &other, &["dam_break"]);

    resumes(&dir, &ck);
}

/// The checkpoint as written still resumes, for one more epoch (a positive control).
fn resumes(dir: &Path, checkpoint: &serde_json::Value) {
    let path = dir.join("out/checkpoint.json");
    std::fs::write(path, serde_json::to_string_pretty(checkpoint).unwrap()).unwrap();
    let ended = optimize(dir, &["--resume", "--epochs", "4"]);
    assert_eq!(ended.code, Some(0), "{}", ended.stderr);
}

/// L-BFGS keeps argmin's solver and state as TOML text inside the checkpoint: parameters of
/// the wrong length or none at all (argmin asserted on the lengths, and our loop unwrapped
/// the missing parameters), correction pairs of the wrong length, a line search configured
/// otherwise than the scene says, and text that is not TOML are each refused.
#[test]
fn lbfgs_checkpoints_with_the_wrong_contents_are_refused() {
    let (dir, ck) = checkpointed("lbfgs", "optimizer = { kind = \"lbfgs\", memory = 5 }");
    let state = ck["optimizer"]["Lbfgs"]["state"].as_str().unwrap().to_string();
    let solver = ck["optimizer"]["Lbfgs"]["solver"].as_str().unwrap().to_string();
    let line = |text: &str, key: &str| -> String {
        text.lines().find(|l| l.starts_with(&format!("{key} = "))).unwrap().to_string()
    };
    let with_state = |state: String| {
        let mut c = ck.clone();
        c["optimizer"]["Lbfgs"]["state"] = state.into();
        c
    };
    let with_solver = |solver: String| {
        let mut c = ck.clone();
        c["optimizer"]["Lbfgs"]["solver"] = solver.into();
        c
    };

    let short = state.replacen(&line(&state, "param"), "param = [0.1, 0.2]", 1);
    resume_refused(&dir, &with_state(short), &["param", "3"]);
    let none = state.replacen(&(line(&state, "param") + "\n"), "", 1);
    resume_refused(&dir, &with_state(none), &["param"]);
    let grad = state.replacen(&line(&state, "grad"), "grad = [1.0]", 1);
    resume_refused(&dir, &with_state(grad), &["grad"]);
    resume_refused(&dir, &with_state("this is not = = toml".into()), &["L-BFGS"]);

    let pairs = solver.replacen(&line(&solver, "s"), "s = [[1.0], [2.0], [3.0]]", 1);
    resume_refused(&dir, &with_solver(pairs), &["s"]);
    let memory = solver.replacen("m = 5", "m = 0", 1);
    resume_refused(&dir, &with_solver(memory), &["m"]);
    let ftol = solver.replacen("ftol = 0.0001", "ftol = -3.0", 1);
    resume_refused(&dir, &with_solver(ftol), &["ftol"]);

    let mut gd = ck.clone();
    gd["optimizer"] = "Gd".into();
    resume_refused(&dir, &gd, &["gradient descent", "L-BFGS"]);
    let mut ahead = ck.clone();
    ahead["next_epoch"] = 2.into();
    resume_refused(&dir, &ahead, &["next_epoch"]);
    resumes(&dir, &ck);
}

/// A checkpoint that is not a file diffluid wrote: not JSON, or a folder, named as a
/// checkpoint (it used to say "cannot read scene file" and "scene ...").
#[test]
fn unreadable_checkpoints_name_the_checkpoint() {
    let (dir, _) = checkpointed("unreadable", "optimizer = { kind = \"gd\", learning_rate = 5.0 }");
    let path = dir.join("out/checkpoint.json");
    for contents in ["{ not json", "[1, 2, 3]"] {
        std::fs::write(&path, contents).unwrap();
        let ended = optimize(&dir, &["--resume"]);
        let line = assert_refused(&ended, &["checkpoint", &path.display().to_string()]);
        assert!(!line.contains("scene"), "{line}");
    }
}

// ---------------------------------------------------------------------------------------
// A run's files, read back by `render`

/// A run folder with `summary` as summary.json and one surface frame (`surface/0000.ply`).
fn run_folder(test: &str, summary: &str, ply: &[u8]) -> TempDir {
    let dir = TempDir::new(test);
    std::fs::write(dir.join("summary.json"), summary).unwrap();
    std::fs::create_dir_all(dir.join("surface")).unwrap();
    std::fs::write(dir.join("surface/0000.ply"), ply).unwrap();
    dir
}

const SUMMARY: &str = r#"{"scene": "crafted", "grid": [8, 8, 8], "dx": 0.05, "dt": 0.01}"#;

/// A PLY header for `vertices` and `faces`, then `data`.
fn ply(vertices: &str, faces: &str, data: &[u8]) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {vertices}\nproperty float x\n\
         property float y\nproperty float z\nelement face {faces}\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    out.extend_from_slice(data);
    out
}

/// One triangle: three vertices, one face.
fn triangle_data() -> Vec<u8> {
    let mut data = Vec::new();
    for p in [[0.1f32, 0.1, 0.1], [0.3, 0.1, 0.1], [0.1, 0.3, 0.1]] {
        for c in p {
            data.extend_from_slice(&c.to_le_bytes());
        }
    }
    data.push(3);
    for i in [0i32, 1, 2] {
        data.extend_from_slice(&i.to_le_bytes());
    }
    data
}

fn render(dir: &Path) -> Ended {
    let out = dir.join("picture.png");
    diffluid(&["render", dir.to_str().unwrap(), "--frame", "0", "--out", out.to_str().unwrap()])
}

/// The valid frame renders (a positive control); a vertex count whose size in bytes wraps
/// around (12 · 2⁶² ≡ 0 mod 2⁶⁴: the size check passed, and the faces then indexed
/// vertices that were never read), counts past the data, and an index past the vertices
/// are refused naming the frame.
#[test]
fn crafted_surface_frames_are_refused() {
    let good = run_folder("ply_good", SUMMARY, &ply("3", "1", &triangle_data()));
    let ended = render(&good);
    assert_eq!(ended.code, Some(0), "{}", ended.stderr);

    let data = triangle_data();
    let wrapping = ply("4611686018427387904", "1", &data[36..]);
    let dir = run_folder("ply_wrap", SUMMARY, &wrapping);
    assert_refused(&render(&dir), &["surface/0000.ply", "4611686018427387904"]);
    let faces = ply("3", "1537228672809129302", &data);
    let dir = run_folder("ply_faces", SUMMARY, &faces);
    assert_refused(&render(&dir), &["surface/0000.ply"]);
    let huge = ply("18446744073709551615", "18446744073709551615", &data);
    let dir = run_folder("ply_huge", SUMMARY, &huge);
    assert_refused(&render(&dir), &["surface/0000.ply"]);
    let mut past = data.clone();
    past[37..41].copy_from_slice(&7i32.to_le_bytes());
    let dir = run_folder("ply_past", SUMMARY, &ply("3", "1", &past));
    assert_refused(&render(&dir), &["surface/0000.ply", "refers past"]);
}

/// A summary whose grid has a zero axis (the picture's height was 0/0 and its allocation
/// aborted), a negative, fractional or missing axis, or a non-positive dx or dt is refused
/// naming summary.json; a tank so tall that the picture would be too is refused saying so.
#[test]
fn crafted_summaries_are_refused() {
    let frame = ply("3", "1", &triangle_data());
    for (n, summary) in [
        r#"{"scene": "s", "grid": [0, 8, 8], "dx": 0.05, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8, 0, 8], "dx": 0.05, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [-8, 8, 8], "dx": 0.05, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8.5, 8, 8], "dx": 0.05, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8, 8], "dx": 0.05, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8, 8, 8], "dx": 0.0, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8, 8, 8], "dx": 1e308, "dt": 0.01}"#,
        r#"{"scene": "s", "grid": [8, 8, 8], "dx": 0.05, "dt": -1.0}"#,
        r#"[]"#,
    ]
    .iter()
    .enumerate()
    {
        let dir = run_folder(&format!("summary_{n}"), summary, &frame);
        assert_refused(&render(&dir), &["summary.json"]);
    }
    let tall = r#"{"scene": "s", "grid": [1, 100000000, 1], "dx": 0.05, "dt": 0.01}"#;
    let dir = run_folder("summary_tall", tall, &frame);
    assert_refused(&render(&dir), &["pixels"]);
}

// ---------------------------------------------------------------------------------------
// Files that are not regular files

/// A scene, a scene's mesh, a checkpoint and a surface frame that are `/dev/zero` (it used to
/// be read until memory ran out) or a FIFO with no writer (opening it waited for ever) are
/// refused as not regular files.
#[test]
fn devices_and_fifos_are_refused() {
    let dir = TempDir::new("special");
    let fifo = dir.join("fifo");
    mkfifo(&fifo);
    let out = dir.join("out");
    let out = out.to_str().unwrap();
    for special in ["/dev/zero", fifo.to_str().unwrap()] {
        let ended = diffluid(&["run", special, "--quiet", "--out", out]);
        assert_refused(&ended, &[special, "not a regular file"]);

        let scene = builtin_text("block_drop");
        let from = "shape = { kind = \"cuboid\", half_extents = [0.1, 0.1, 0.1] }";
        assert!(scene.contains(from), "block_drop.toml changed");
        let text = scene.replacen(
            from,
            &format!("shape = {{ kind = \"mesh\", obj = \"{special}\", scale = 1.0 }}"),
            1,
        );
        let path = dir.join("mesh.toml");
        std::fs::write(&path, text).unwrap();
        let ended = diffluid(&["run", path.to_str().unwrap(), "--quiet", "--out", out]);
        assert_refused(&ended, &[special, "not a regular file"]);
    }

    // A checkpoint and a surface frame, as links to each.
    let (ck_dir, _) =
        checkpointed("special_ck", "optimizer = { kind = \"gd\", learning_rate = 5.0 }");
    let run = run_folder("special_ply", SUMMARY, b"");
    for special in [Path::new("/dev/zero"), fifo.as_path()] {
        let ck = ck_dir.join("out/checkpoint.json");
        std::fs::remove_file(&ck).unwrap();
        std::os::unix::fs::symlink(special, &ck).unwrap();
        let ended = optimize(&ck_dir, &["--resume"]);
        assert_refused(&ended, &["checkpoint", "not a regular file"]);

        let frame = run.join("surface/0000.ply");
        std::fs::remove_file(&frame).unwrap();
        std::os::unix::fs::symlink(special, &frame).unwrap();
        assert_refused(&render(&run), &["surface/0000.ply", "not a regular file"]);
    }
}
