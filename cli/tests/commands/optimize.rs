//! Optimisation: recovering a known initial velocity, resuming an interrupted run, and a run
//! its caller interrupts.
//!
//! Recovery: the target is the final state of a forward run from v*; gradient descent from
//! rest on the exact gradient (surface held fixed) must find v* again, within 1%, and so must
//! L-BFGS, in fewer loss-and-gradient evaluations than Adam.
//! Resume: the optimiser writes a checkpoint (parameters, optimiser state, history) after
//! every epoch, atomically; a run killed with SIGKILL mid-way and resumed must end with the
//! same parameters, bit for bit, as one never interrupted, for gradient descent and L-BFGS.

use crate::common::{builtin_text, EXE};
use diffluid::experiments::optimize::Optimization;
use diffluid::geometry::body::BodyState;
use diffluid::Scene;
use std::process::Command;
use std::time::Duration;

#[test]
fn recovers_the_initial_velocity_within_one_percent() {
    let scene = Scene::builtin("recover_box").unwrap();
    let vstar = scene.optimize.as_ref().unwrap().recover_velocity.unwrap();
    let problem = Optimization::new(scene).unwrap();
    let out = problem.run(None, None, |_| {}).unwrap();
    assert!(out.stopped.is_none());
    let v = out.params.v;
    let err = ((0..3).map(|d| (v[d] - vstar[d]).powi(2)).sum::<f64>()
        / vstar.iter().map(|x| x * x).sum::<f64>())
    .sqrt();
    eprintln!(
        "recovered v0 = {v:?} (v* = {vstar:?}), relative error {err:.2e}, loss {:.2e}",
        out.final_loss
    );
    assert!(err < 0.01, "relative error {err}");
}

/// The recovery scene with another optimiser.
fn recover_box_with(optimizer: &str) -> String {
    let base = builtin_text("recover_box");
    let from = "optimizer = { kind = \"gd\", learning_rate = 5.0 }";
    assert!(base.contains(from));
    base.replacen(from, &format!("optimizer = {optimizer}"), 1)
}

fn relative_error(p: &BodyState, vstar: [f64; 3]) -> f64 {
    ((0..3).map(|d| (p.v[d] - vstar[d]).powi(2)).sum::<f64>()
        / vstar.iter().map(|x| x * x).sum::<f64>())
    .sqrt()
}

/// L-BFGS (argmin, Moré–Thuente) finds v* within 1%, and needs fewer loss-and-gradient
/// evaluations for it than Adam: Adam run for as many epochs (one evaluation each) as L-BFGS
/// used evaluations is still more than 1% away. Measured: L-BFGS within 1% after 9
/// evaluations (epoch 8) and to 1e-9 after 13; Adam first within 1% after 79 (lr 0.2) or 74
/// (lr 0.05) evaluations, not within 60 at lr 0.1; the scene's GD 5.0 after 39.
#[test]
fn lbfgs_recovers_the_initial_velocity_in_fewer_evaluations_than_adam() {
    let scene = Scene::from_toml(&recover_box_with("{ kind = \"lbfgs\" }"), "<lbfgs>").unwrap();
    let vstar = scene.optimize.as_ref().unwrap().recover_velocity.unwrap();
    let lbfgs = Optimization::new(scene).unwrap().run(None, None, |_| {}).unwrap();
    assert!(lbfgs.stopped.is_none(), "{:?}", lbfgs.stopped);
    let err = relative_error(&lbfgs.params, vstar);
    assert!(err < 0.01, "L-BFGS ended {err:e} from v*");
    // The evaluations spent when the parameters were first within 1%.
    let needed = lbfgs
        .history
        .iter()
        .find(|r| relative_error(&r.params, vstar) < 0.01)
        .map(|r| r.evaluations)
        .unwrap_or(lbfgs.evaluations);
    let adam_scene =
        Scene::from_toml(&recover_box_with("{ kind = \"adam\", learning_rate = 0.1 }"), "<adam>")
            .unwrap();
    let mut adam = Optimization::new(adam_scene).unwrap();
    adam.epochs = needed;
    let out = adam.run(None, None, |_| {}).unwrap();
    let adam_best =
        out.history.iter().map(|r| relative_error(&r.params, vstar)).fold(f64::INFINITY, f64::min);
    eprintln!(
        "L-BFGS: within 1% after {needed} evaluations, {err:.1e} after {} (loss {:.1e}); \
         Adam 0.1 after {needed}: best {adam_best:.1e}",
        lbfgs.evaluations, lbfgs.final_loss
    );
    assert!(adam_best >= 0.01, "Adam was within 1% in {needed} evaluations too");
}

fn run_cli(scene: &str, dir: &std::path::Path, extra: &[&str]) -> std::process::Child {
    Command::new(EXE)
        .args(["optimize", scene, "--epochs", "8", "--quiet", "--out"])
        .arg(dir)
        .args(extra)
        .spawn()
        .unwrap()
}

fn params(dir: &std::path::Path) -> serde_json::Value {
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("result.json")).unwrap()).unwrap();
    v["params"].clone()
}

fn killed_and_resumed(scene: &str, base: &std::path::Path) {
    let (a, b) = (base.join("straight"), base.join("killed"));
    std::fs::create_dir_all(base).unwrap();
    assert!(run_cli(scene, &a, &[]).wait().unwrap().success());
    // Kill the second run with SIGKILL once a few epochs are checkpointed.
    let mut child = run_cli(scene, &b, &[]);
    let ck = b.join("checkpoint.json");
    let mut waited = 0;
    loop {
        std::thread::sleep(Duration::from_millis(50));
        waited += 50;
        let epochs = std::fs::read_to_string(&ck)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v["next_epoch"].as_u64())
            .unwrap_or(0);
        if epochs >= 3 || waited > 120_000 {
            break;
        }
    }
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert!(!status.success(), "the run must have been killed mid-way");
    assert!(!b.join("result.json").exists(), "killed before the end");
    assert!(run_cli(scene, &b, &["--resume"]).wait().unwrap().success());
    assert_eq!(params(&a), params(&b), "resumed run ended elsewhere");
    let csv = |d: &std::path::Path| std::fs::read_to_string(d.join("loss.csv")).unwrap();
    assert_eq!(csv(&a), csv(&b), "resumed run has another history");
}

#[test]
fn a_run_killed_and_resumed_ends_where_an_uninterrupted_one_does() {
    let base = std::env::temp_dir().join(format!("diffluid-resume-{}", std::process::id()));
    killed_and_resumed("recover_box", &base);
    std::fs::remove_dir_all(&base).ok();
}

/// The same for L-BFGS, whose checkpoint holds argmin's solver (correction pairs, line
/// search) and iteration state.
#[test]
fn an_lbfgs_run_killed_and_resumed_ends_where_an_uninterrupted_one_does() {
    let base = std::env::temp_dir().join(format!("diffluid-resume-lbfgs-{}", std::process::id()));
    std::fs::create_dir_all(&base).unwrap();
    let scene = base.join("recover_lbfgs.toml");
    std::fs::write(&scene, recover_box_with("{ kind = \"lbfgs\", memory = 5 }")).unwrap();
    killed_and_resumed(scene.to_str().unwrap(), &base);
    std::fs::remove_dir_all(&base).ok();
}

/// Bad optimisation settings are rejected with a message naming the key.
#[test]
fn bad_optimisation_input_is_rejected() {
    let base = builtin_text("recover_box");
    let cases = [
        ("params = [\"v\"]", "params = [\"speed\"]", "unknown parameter \"speed\""),
        ("learning_rate = 5.0", "learning_rate = -1.0", "optimize.optimizer.learning_rate"),
        ("kind = \"gd\"", "kind = \"newton\"", "unknown variant `newton`"),
        (
            "{ kind = \"gd\", learning_rate = 5.0 }",
            "{ kind = \"lbfgs\", memory = 0 }",
            "optimize.optimizer.memory",
        ),
        (
            "{ kind = \"gd\", learning_rate = 5.0 }",
            "{ kind = \"lbfgs\", tolerance_grad = -1.0 }",
            "optimize.optimizer.tolerance_grad",
        ),
        (
            "{ kind = \"gd\", learning_rate = 5.0 }",
            "{ kind = \"lbfgs\", learning_rate = 1.0 }",
            "unknown field `learning_rate`",
        ),
        ("learning_rate = 5.0", "learning_rate = 5.0, decay = 0.0", "optimize.optimizer.decay"),
        ("learning_rate = 5.0", "learning_rate = 5.0, decay = 1.5", "optimize.optimizer.decay"),
        ("epochs = 60", "epochs = 0", "optimize.epochs"),
        (
            "epochs = 60",
            "epochs = 60\nsmoothing = { samples = 4, sigma = { x = 0.01 }, estimator = \"values\" }",
            "optimize.smoothing.sigma.v",
        ),
        (
            "epochs = 60",
            "epochs = 60\nsmoothing = { samples = 4, sigma = { v = 0.01 }, sigma_decay = 1.2 }",
            "sigma_decay must be in (0, 1]",
        ),
        (
            "{ kind = \"gd\", learning_rate = 5.0 }",
            "{ kind = \"lbfgs\" }\nsmoothing = { samples = 4, sigma = { v = 0.01 }, sigma_decay = 0.9 }",
            "optimize.smoothing.sigma_decay",
        ),
        (
            "epochs = 60",
            "epochs = 60\nsmoothing = { samples = 4, sigma = { v = 0.01 }, estimator = \"guess\" }",
            "unknown variant `guess`",
        ),
        ("target = [0.4, 0.2, 0.4]", "target = [0.4, 2.0, 0.4]", "outside the tank"),
        ("body = \"box\"", "body = \"crate\"", "no body named \"crate\""),
    ];
    for (from, to, needle) in cases {
        assert!(base.contains(from), "the base scene lacks {from:?}");
        let text = base.replacen(from, to, 1);
        let err = Scene::from_toml(&text, "<test>").unwrap_err().to_string();
        assert!(err.contains(needle), "{to:?}: message {err:?} lacks {needle:?}");
    }
    // Through the CLI: one line, non-zero exit.
    let dir = std::env::temp_dir().join(format!("diffluid-badopt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bad.toml");
    std::fs::write(&path, base.replacen("params = [\"v\"]", "params = [\"speed\"]", 1)).unwrap();
    let out = Command::new(EXE)
        .args(["optimize"])
        .arg(&path)
        .args(["--quiet", "--out"])
        .arg(dir.join("out"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(stderr.starts_with("error:") && stderr.contains("optimize.params"), "{stderr}");
    std::fs::remove_dir_all(dir).ok();
}

/// The paper's block drop: plain gradient descent with learning rate 1.0 on v and ω for 50
/// epochs brings the loss down 2798× (measured; the paper's Figure 2 falls about 100×); held
/// to within 10× of that.
#[test]
fn block_drop_loss_falls_nearly_three_thousandfold_in_fifty_epochs() {
    let problem = Optimization::new(Scene::builtin("block_drop").unwrap()).unwrap();
    assert_eq!(problem.epochs, 50);
    let out = problem.run(None, None, |_| {}).unwrap();
    assert!(out.stopped.is_none(), "{:?}", out.stopped);
    // Without smoothing the loss is L itself, and no second one is recorded.
    assert!(out.history.iter().all(|r| r.unsmoothed_loss.is_none()));
    let first = out.history[0].loss;
    eprintln!(
        "block drop: loss {first:.3e} -> {:.3e} ({:.0}x)",
        out.final_loss,
        first / out.final_loss
    );
    assert!(out.final_loss * 280.0 < first, "loss fell only {}x", first / out.final_loss);
}

/// Why the dam break with a ball cannot fall 10×: contact has no restitution and the collapsed
/// water is about 3.5 cm deep (0.28 m³ over 8 m²), too shallow to float a ball of radius
/// 0.2 m, so at t = 2.5 s the ball rests on the floor with its centre at y = 0.2, 0.4 m below
/// the target's 0.6. The loss is then at least 0.4² = 0.16, and the start's 1.590 can fall at
/// most 9.9×. Checked from rest, from a velocity Adam (lr 0.3) once found at loss 0.161 (1.83
/// on today's map), and from the one the scene's own optimisation ends at (loss 0.1603,
/// issue 37).
#[test]
fn dam_break_ball_ends_on_the_floor_so_its_loss_is_at_least_0_16() {
    let problem = Optimization::new(Scene::builtin("dam_break_ball").unwrap()).unwrap();
    for v in [
        [0.0; 3],
        [2.356917571565773, 2.453500736110804, -0.7403118479015697],
        [0.9434906400641141, -0.9691371887701522, -0.292924484141406],
    ] {
        let mut p = problem.initial_params();
        p.v = v.into();
        let mut sim = problem.simulation(&p);
        for _ in 0..problem.scene.time.steps {
            sim.step().unwrap();
        }
        let y = sim.bodies()[problem.body].x.y;
        let loss = problem.loss_at(&p).unwrap();
        eprintln!("v0 {v:?}: final y {y:.5}, loss {loss:.4}");
        assert!((y - 0.2).abs() < 1e-3, "v0 {v:?}: the ball ends at y = {y}");
        assert!(loss > 0.16 - 1e-3, "v0 {v:?}: loss {loss}");
    }
}

/// A run that goes wrong stops with a reason and keeps the last good parameters: gradient
/// descent at learning rate 200 throws the box out of the tank on its second epoch (the
/// first gradient, norm 0.108, becomes a 21 m/s step), and L-BFGS with max_gradient_norm
/// 0.1 stops on its first gradient (norm 0.108, exploding by that threshold).
#[test]
fn a_failed_run_stops_and_keeps_the_last_good_parameters() {
    let scene =
        Scene::from_toml(&recover_box_with("{ kind = \"gd\", learning_rate = 200.0 }"), "<gd200>")
            .unwrap();
    let problem = Optimization::new(scene).unwrap();
    let out = problem.run(None, None, |_| {}).unwrap();
    let reason = out.stopped.expect("the run must stop");
    assert!(reason.starts_with("epoch 1:") && reason.contains("left the tank"), "{reason}");
    assert_eq!(out.history.len(), 1);
    assert_eq!(out.params, problem.initial_params());
    assert_eq!(out.final_loss, out.history[0].loss);

    let text = recover_box_with("{ kind = \"lbfgs\" }").replacen(
        "epochs = 60",
        "epochs = 60\nmax_gradient_norm = 0.1",
        1,
    );
    let problem = Optimization::new(Scene::from_toml(&text, "<lbfgs>").unwrap()).unwrap();
    let out = problem.run(None, None, |_| {}).unwrap();
    let reason = out.stopped.expect("the run must stop");
    assert!(reason.contains("exploding") && reason.contains("last good"), "{reason}");
    assert_eq!(out.params, problem.initial_params());
}

/// A checkpoint resumes only the run that wrote it: with the learning rate, the optimiser,
/// the optimised parameters or the scene changed, `--resume` is refused with the key that
/// changed (it used to check only the scene's name and went on with the new settings).
#[test]
fn resume_refuses_a_changed_setting_and_names_it() {
    let dir = std::env::temp_dir().join(format!("diffluid-resume-check-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let ck = dir.join("checkpoint.json");
    let mut scene = Scene::builtin("recover_box").unwrap();
    scene.time.steps = 4;
    scene.optimize.as_mut().unwrap().epochs = 2;
    Optimization::new(scene.clone()).unwrap().run(Some(&ck), None, |_| {}).unwrap();
    let resume = |s: &Scene| {
        let c = diffluid::experiments::optimize::Checkpoint::load(&ck).unwrap();
        Optimization::new(s.clone()).unwrap().run(Some(&dir.join("other.json")), Some(c), |_| {})
    };
    // More epochs are fine: that is what resuming is for.
    let mut more = scene.clone();
    more.optimize.as_mut().unwrap().epochs = 3;
    assert!(resume(&more).is_ok());
    let mut lr = scene.clone();
    lr.optimize.as_mut().unwrap().optimizer =
        diffluid::experiments::scene::OptimizerSpec::Gd { learning_rate: 2.0, decay: 1.0 };
    let err = resume(&lr).unwrap_err().to_string();
    assert!(err.contains("optimize.optimizer.learning_rate") && err.contains("5.0"), "{err}");
    let mut params = scene.clone();
    params.optimize.as_mut().unwrap().params.push(diffluid::geometry::body::Param::W);
    let err = resume(&params).unwrap_err().to_string();
    assert!(err.contains("optimize.params"), "{err}");
    let mut dense = scene.clone();
    dense.body[0].density = Some(700.0);
    let err = resume(&dense).unwrap_err().to_string();
    assert!(err.contains("body"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Adam where it works: at lr 0.2 it finds v* within 1% (measured after 79 evaluations; the
/// other Adam test runs it at lr 0.1, where it does not get there in time).
#[test]
fn adam_at_a_working_rate_recovers_the_initial_velocity() {
    let scene =
        Scene::from_toml(&recover_box_with("{ kind = \"adam\", learning_rate = 0.2 }"), "<adam>")
            .unwrap();
    let vstar = scene.optimize.as_ref().unwrap().recover_velocity.unwrap();
    let mut problem = Optimization::new(scene).unwrap();
    problem.epochs = 90;
    let out = problem.run(None, None, |_| {}).unwrap();
    let first =
        out.history.iter().find(|r| relative_error(&r.params, vstar) < 0.01).map(|r| r.evaluations);
    eprintln!("Adam 0.2: within 1% of v* after {first:?} evaluations");
    assert!(first.is_some_and(|n| n <= 90), "Adam 0.2 not within 1% in 90 evaluations");
}

/// A run its caller interrupts after an epoch (Ctrl-C seen from Python) stops there with
/// every record so far, the same records as the run not interrupted, and that epoch's
/// parameters and loss as its result; for gradient descent and L-BFGS.
#[test]
fn an_interrupted_run_keeps_its_history() {
    for optimizer in ["{ kind = \"gd\", learning_rate = 5.0 }", "{ kind = \"lbfgs\" }"] {
        let mut scene = Scene::from_toml(&recover_box_with(optimizer), "<interrupt>").unwrap();
        scene.time.steps = 6;
        scene.optimize.as_mut().unwrap().epochs = 5;
        let problem = Optimization::new(scene).unwrap();
        let whole = problem.run(None, None, |_| {}).unwrap();
        let mut seen = 0;
        let cut = problem
            .run_while(None, None, |_| {
                seen += 1;
                if seen == 3 {
                    std::ops::ControlFlow::Break(())
                } else {
                    std::ops::ControlFlow::Continue(())
                }
            })
            .unwrap();
        assert_eq!(cut.history[..], whole.history[..3], "{optimizer}");
        let stopped = cut.stopped.as_deref().unwrap_or_default();
        assert!(stopped.contains("epoch 2: interrupted"), "{stopped}");
        assert_eq!(cut.params, cut.history[2].params);
        assert_eq!(cut.final_loss, cut.history[2].loss);
    }
}

/// `--epochs` counts every epoch, those before the checkpoint too: with `--resume` it must
/// go past them, or the run would do nothing and say it ran (`--resume --epochs 10` after 50
/// epochs silently ran none).
#[test]
fn resume_with_no_epochs_left_is_refused() {
    let dir = std::env::temp_dir().join(format!("diffluid-resume-epochs-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let optimize = |args: &[&str]| {
        Command::new(EXE)
            .args(["optimize", "recover_box", "--quiet", "--out"])
            .arg(&dir)
            .args(args)
            .output()
            .unwrap()
    };
    assert!(optimize(&["--epochs", "2"]).status.success());
    for (epochs, needle) in [("1", "--epochs 1"), ("2", "--epochs 2")] {
        let refused = optimize(&["--epochs", epochs, "--resume"]);
        let stderr = String::from_utf8_lossy(&refused.stderr);
        assert_eq!(refused.status.code(), Some(1), "{stderr}");
        assert!(stderr.starts_with("error: ") && stderr.lines().count() == 1, "{stderr}");
        assert!(stderr.contains(needle) && stderr.contains("2 epochs"), "{stderr}");
    }
    assert!(optimize(&["--epochs", "3", "--resume"]).status.success());
    let result: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("result.json")).unwrap()).unwrap();
    assert_eq!(result["epochs"], 3);
    std::fs::remove_dir_all(&dir).ok();
}
