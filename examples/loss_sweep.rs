//! Where the forward map jumps: the loss along one initial coordinate of a scene's first
//! body, sampled finely, and its roughness; or two runs stepped side by side to find the step
//! and the cells where they part.
//!
//! ```text
//! cargo run --release --example loss_sweep -- SCENE STEPS SETTINGS HALF
//! cargo run --release --example loss_sweep -- SCENE STEPS SETTINGS --pair T1 T2
//! cargo run --release --example loss_sweep -- SCENE STEPS SETTINGS --volume
//! cargo run --release --example loss_sweep -- SCENE STEPS SETTINGS --kink T1 T2 T3
//! cargo run --release --example loss_sweep -- SCENE STEPS SETTINGS --spreads K
//! ```
//!
//! `SCENE` is a built-in scene or a file with a `[loss]`; `SETTINGS` a comma-separated list of
//! `default`, `no-density`, `sparse`, `no-sparse`, `substeps=N`, `volume-control=K`, `theta-min=X`,
//! `close-pockets=K`, `sparse-depth=D`, `tolerance=X`, `density-tolerance=X`, `density-gain=G`,
//! `density-passes=N`, `density-face-ramp=W`, `surface-softness=T`, `body-ramp`, `surface-blend=T`, `smooth` (`surface-blend=0.5`,
//! `body-ramp`, `close-pockets=0.5`, `no-sparse`, `theta-min=1e-5`: the defaults since
//! 6 December 2026), `yes-no` (the surface rules that were the defaults before: no blend, no
//! ramp, pockets open, the sparse-cell rule, θ clamped at 0.01), and
//! `along=P` (the coordinate moved: `v0` … `q2`, default `v0`). The sweep runs the scene at
//! that coordinate + t for 41 values of t over ±`HALF` (in parallel) and prints the median slope, the net slope and the roughness: the sum of
//! the 40 steps' deviations from the median step over the net change (0 for a line, about 1
//! or more where jumps dominate). `--pair` steps the runs at t = T1 and T2 together and
//! prints, per step, how far the body's position and velocity differ, how many cells differ
//! in kind, and each such cell with its φ in both runs and its neighbours' φ; then how far
//! the marker particles, φ and the face velocities differ at most, and where (a jump that
//! changes no cell's kind shows there first, often far from the body). `--volume` runs the
//! scene once and prints its worst liquid-volume error over the steps, the step, and the
//! last step's. `--kink` steps three runs at equally spaced t together and prints, per step,
//! the largest second differences of the body's velocity, the particles, φ, the face
//! velocities and the body's face fractions against their first differences: about 0 where
//! the map is smooth between the three, of the order of the first where it kinks, so the
//! first step that shows one names where a kink of the sweep comes from. `--spreads K`
//! measures the central differences' spread |fd(1e-4) − fd(1e-6)|/|fd(1e-6)| of every
//! initial coordinate at K starting points each and prints each coordinate's median and
//! worst and, over all of them, the share of samples above 1% and 5%: the smoothness
//! targets' measure, over enough samples that one does not decide.
//! docs/gradients.md ("Air pockets") quotes what it measured.

use diffluid::experiments::scene::Scene;
use diffluid::geometry::body::Param;
use diffluid::gradients::Loss;
use diffluid::math::pool::side_by_side;
use diffluid::math::Vec3;
use diffluid::world::{Simulation, StepRecord, Tape};
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage =
        "usage: loss_sweep SCENE STEPS SETTINGS (HALF | --pair T1 T2 | --volume | --kink T1 T2 T3 | --spreads K)";
    if args.len() < 4 {
        return Err(usage.into());
    }
    let mut scene = if Path::new(&args[0]).exists() {
        Scene::from_file(Path::new(&args[0]))?
    } else {
        Scene::builtin(&args[0])?
    };
    let steps: usize = args[1].parse()?;
    let mut along = (Param::V, 0);
    for setting in args[2].split(',') {
        let (key, value) = setting.split_once('=').unwrap_or((setting, ""));
        let s = &mut scene.solver;
        match key {
            "default" => {}
            "body-ramp" => s.body_ramp = true,
            "yes-no" => s.use_yes_no_surface_rules(),
            "smooth" => s.use_smooth_surface_rules(),
            "surface-blend" => s.surface_blend = value.parse()?,
            "along" => along = parse_along(value)?,
            "no-density" => s.density_correction = false,
            "no-sparse" => s.sparse_cells = false,
            "sparse" => s.sparse_cells = true,
            "substeps" => s.particle_substeps = value.parse()?,
            "volume-control" => s.volume_control = Some(value.parse()?),
            "theta-min" => s.theta_min = value.parse()?,
            "close-pockets" => s.close_pockets = Some(value.parse()?),
            "sparse-depth" => s.sparse_depth = value.parse()?,
            "surface-softness" => s.surface_softness = value.parse()?,
            "density-tolerance" => s.density_tolerance = value.parse()?,
            "tolerance" => s.tolerance = value.parse()?,
            "density-gain" => s.density_gain = value.parse()?,
            "density-passes" => s.density_passes = value.parse()?,
            "density-face-ramp" => s.density_face_ramp = value.parse()?,
            other => return Err(format!("unknown setting {other}").into()),
        }
    }
    if args[3] == "--volume" {
        return volume(scene.build()?, steps).map_err(Into::into);
    }
    let loss = scene.loss().ok_or("the scene has no [loss]")?;
    let sim = scene.build()?;
    let start = |t: f64| -> diffluid::Result<Simulation> {
        let mut s = sim.clone();
        let h = s.handles()[0];
        let state = along.0.perturbed(&s.bodies()[0].state(), along.1, t);
        s.set_body_state(h, &state)?;
        Ok(s)
    };
    if args[3] == "--pair" {
        let t: Vec<f64> = args[4..].iter().map(|x| x.parse()).collect::<Result<_, _>>()?;
        let [t1, t2] = t[..] else { return Err(usage.into()) };
        return pair(start(t1)?, start(t2)?, steps).map_err(Into::into);
    }
    if args[3] == "--spreads" {
        let k: usize = args.get(4).map(|x| x.parse()).transpose()?.unwrap_or(5);
        return spreads(&sim, &loss, steps, k).map_err(Into::into);
    }
    if args[3] == "--kink" {
        let t: Vec<f64> = args[4..].iter().map(|x| x.parse()).collect::<Result<_, _>>()?;
        let [t1, t2, t3] = t[..] else { return Err(usage.into()) };
        return kink([start(t1)?, start(t2)?, start(t3)?], steps).map_err(Into::into);
    }
    let half: f64 = args[3].parse()?;
    let n = 20;
    let ts: Vec<f64> = (-n..=n).map(|k| half * k as f64 / n as f64).collect();
    let losses: Vec<f64> = side_by_side(&ts, |&t| {
        let mut s = start(t)?;
        for _ in 0..steps {
            s.step()?;
        }
        Ok(loss.value(&s))
    })
    .into_iter()
    .collect::<diffluid::Result<_>>()?;
    let d: Vec<f64> = losses.windows(2).map(|w| w[1] - w[0]).collect();
    let mut sorted = d.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let net = losses[losses.len() - 1] - losses[0];
    let rough: f64 = d.iter().map(|x| (x - median).abs()).sum();
    let h = half / n as f64;
    println!(
        "{} {steps} steps, {}: median slope {:.4e}, net slope {:.4e}, roughness {:.3}",
        scene.name,
        args[2],
        median / h,
        net / (2.0 * half),
        rough / net.abs()
    );
    for (t, x) in ts.iter().zip(&d) {
        println!("  t {t:+.2e}: slope {:+.4e}", x / h);
    }
    Ok(())
}

/// The central differences' spread |fd(1e-4) − fd(1e-6)| / |fd(1e-6)| of every initial
/// coordinate of the first body, at `k` starting points along it (offsets of 3.7e-5 m or
/// rad, or m/s, apart, so that one lucky or unlucky sample does not decide): per coordinate
/// the median and the worst, and over all the samples the share above 1% and 5%.
fn spreads(sim: &Simulation, loss: &dyn Loss, steps: usize, k: usize) -> diffluid::Result<()> {
    let coords: Vec<(Param, usize)> =
        Param::ALL.into_iter().flat_map(|p| (0..3).map(move |a| (p, a))).collect();
    let offsets: Vec<f64> = (0..k).map(|i| 3.7e-5 * i as f64).collect();
    let hs = [1e-4, -1e-4, 1e-6, -1e-6];
    let jobs: Vec<(usize, usize, usize)> = (0..coords.len())
        .flat_map(|c| (0..k).flat_map(move |o| (0..4).map(move |h| (c, o, h))))
        .collect();
    let values: Vec<f64> = side_by_side(&jobs, |&(c, o, h)| {
        let (p, a) = coords[c];
        let mut s = sim.clone();
        let id = s.handles()[0];
        let state = p.perturbed(&s.bodies()[0].state(), a, offsets[o] + hs[h]);
        s.set_body_state(id, &state)?;
        for _ in 0..steps {
            s.step()?;
        }
        Ok(loss.value(&s))
    })
    .into_iter()
    .collect::<diffluid::Result<_>>()?;
    // Per coordinate and start: (spread, |fd(1e-6)|).
    let rows: Vec<Vec<(f64, f64)>> = (0..coords.len())
        .map(|c| {
            (0..k)
                .map(|o| {
                    let v = &values[(c * k + o) * 4..][..4];
                    let coarse = (v[0] - v[1]) / 2e-4;
                    let fine = (v[2] - v[3]) / 2e-6;
                    ((coarse - fine).abs() / fine.abs(), fine.abs())
                })
                .collect()
        })
        .collect();
    let largest = rows.iter().flatten().map(|r| r.1).fold(0.0, f64::max);
    let mut all = Vec::new();
    for ((p, a), row) in coords.iter().zip(&rows) {
        let mut sorted: Vec<f64> = row.iter().map(|r| r.0).collect();
        sorted.sort_by(f64::total_cmp);
        let size = row.iter().map(|r| r.1).sum::<f64>() / k as f64;
        // A row under a hundredth of the largest (a ball's spin, a symmetric axis) is
        // the differences' noise over a slope of nearly nothing: shown, not counted.
        let counted = size >= 1e-2 * largest;
        if counted {
            all.extend(sorted.iter().copied());
        }
        println!(
            "{}{a}: |fd| {size:.3e}, median spread {:.2}%, worst {:.2}%{}",
            p.name(),
            100.0 * sorted[sorted.len() / 2],
            100.0 * sorted[sorted.len() - 1],
            if counted { "" } else { " (under 1% of the largest row: not counted)" }
        );
    }
    all.sort_by(f64::total_cmp);
    let share = |t: f64| all.iter().filter(|&&x| x > t).count() as f64 / all.len() as f64;
    println!(
        "{} samples counted: median spread {:.2}%, above 1%: {:.0}%, above 5%: {:.0}%",
        all.len(),
        100.0 * all[all.len() / 2],
        100.0 * share(0.01),
        100.0 * share(0.05)
    );
    Ok(())
}

/// `v0` … `q2`: the parameter and axis the sweep moves along.
fn parse_along(value: &str) -> Result<(Param, usize), String> {
    let bad = || format!("along={value}: expected v, w, x or q and an axis 0–2, as x2");
    let (name, axis) = value.split_at_checked(1).ok_or_else(bad)?;
    let param = Param::ALL.into_iter().find(|p| p.name() == name).ok_or_else(bad)?;
    let axis: usize = axis.parse().map_err(|_| bad())?;
    if axis > 2 {
        return Err(bad());
    }
    Ok((param, axis))
}

/// Steps `sim` and prints its worst relative liquid-volume error and the step of it.
fn volume(mut sim: Simulation, steps: usize) -> diffluid::Result<()> {
    let v0 = sim.liquid_volume();
    let (mut worst, mut at, mut last) = (0.0f64, 0, 0.0);
    for k in 1..=steps {
        last = (sim.step()?.liquid_volume - v0).abs() / v0;
        if last > worst {
            (worst, at) = (last, k);
        }
    }
    println!(
        "worst volume error {:.3}% at step {at} of {steps}, {:.3}% at the last",
        100.0 * worst,
        100.0 * last
    );
    Ok(())
}

/// Steps `a` and `b` together and prints where they part.
fn pair(mut a: Simulation, mut b: Simulation, steps: usize) -> diffluid::Result<()> {
    let grid = *a.grid();
    for k in 1..=steps {
        let (ra, rb) = (a.step()?, b.step()?);
        let (sa, sb) = (a.bodies()[0].state(), b.bodies()[0].state());
        let (pa, pb) = (a.liquid_phi(), b.liquid_phi());
        let changed: Vec<usize> =
            (0..pa.len()).filter(|&c| (pa[c] < 0.0) != (pb[c] < 0.0)).collect();
        println!(
            "step {k:3}: |Δx| {:.3e} |Δv| {:.3e}, {} cells of another kind, liquid cells {} / {}",
            (sa.x - sb.x).length(),
            (sa.v - sb.v).length(),
            changed.len(),
            ra.liquid_cells,
            rb.liquid_cells
        );
        for c in changed.iter().copied() {
            let [i, j, l] = grid.cells().ijk(c);
            let around: Vec<String> = (0..3)
                .flat_map(|axis| (0..2).map(move |side| (axis, side)))
                .map(|(axis, side)| {
                    let mut n = [i, j, l];
                    if side == 0 && n[axis] == 0 || side == 1 && n[axis] + 1 == grid.n[axis] {
                        return "wall".to_string();
                    }
                    n[axis] = if side == 0 { n[axis] - 1 } else { n[axis] + 1 };
                    format!("{:+.3}", pb[grid.cell(n[0], n[1], n[2])] / grid.dx)
                })
                .collect();
            println!(
                "  cell ({i}, {j}, {l}): φ/dx {:+.3e} and {:+.3e}; neighbours' φ/dx (−x +x −y +y −z +z, second run) {}",
                pa[c] / grid.dx,
                pb[c] / grid.dx,
                around.join(" ")
            );
        }
        let apart = a.particles().iter().zip(b.particles()).map(|(x, y)| (*x - *y).length());
        let (p, far) = largest(apart);
        let at = a.particles().get(p).map(|x| x.to_array());
        let (c, dphi) = largest((0..pa.len()).map(|c| (pa[c] - pb[c]).abs()));
        let (ua, ub) = (a.velocity_field(), b.velocity_field());
        let (axis, (f, du)) = (0..3)
            .map(|k| (k, largest(ua.c[k].iter().zip(&ub.c[k]).map(|(x, y)| (x - y).abs()))))
            .max_by(|x, y| x.1 .1.total_cmp(&y.1 .1))
            .expect("three axes");
        println!(
            "  at most: particles {far:.3e} m apart (particle {p} at {at:.4?}), φ/dx {:.3e} at cell {:?}, u {du:.3e} m/s at face {:?} of axis {axis}",
            dphi / grid.dx,
            grid.cells().ijk(c),
            grid.faces(axis).ijk(f)
        );
    }
    Ok(())
}

/// Steps three runs (at equally spaced values of the coordinate) together and prints, per
/// step, the largest second differences |a − 2b + c| of the body's velocity, the particles,
/// φ, the face velocities and the body's face fractions against the first |a − c| (about 0
/// where the map is smooth between them, of the order of the first where it kinks), and
/// where: the step and the place a kink comes from.
fn kink(mut s: [Simulation; 3], steps: usize) -> diffluid::Result<()> {
    let grid = *s[0].grid();
    for k in 1..=steps {
        let mut recs = Vec::new();
        for sim in s.iter_mut() {
            let mut tape = Tape::default();
            sim.step_taped(&mut tape)?;
            recs.push(tape.steps.pop().expect("a taped step"));
        }
        let [a, b, c] = &s;
        let body = &b.bodies()[0];
        let (pa, pb, pc) = (a.particles(), b.particles(), c.particles());
        let second = |x: Vec3, y: Vec3, z: Vec3| (x - 2.0 * y + z).length();
        let (p, dp) = largest((0..pa.len()).map(|i| second(pa[i], pb[i], pc[i])));
        let first = largest((0..pa.len()).map(|i| (pa[i] - pc[i]).length())).1;
        let fb = b.liquid_phi();
        let (cell, dphi, phi_first) = differences(a.liquid_phi(), fb, c.liquid_phi());
        let (ua, ub, uc) = (a.velocity_field(), b.velocity_field(), c.velocity_field());
        let per_axis: Vec<_> = (0..3).map(|d| differences(&ua.c[d], &ub.c[d], &uc.c[d])).collect();
        let u_first = per_axis.iter().map(|x| x.2).fold(0.0, f64::max);
        let (axis, &(f, du, _)) = per_axis
            .iter()
            .enumerate()
            .max_by(|x, y| x.1 .1.total_cmp(&y.1 .1))
            .expect("three axes");
        let (va, vb, vc) = (a.bodies()[0].state().v, body.state().v, c.bodies()[0].state().v);
        let at = pb.get(p).copied().unwrap_or(Vec3::ZERO);
        let fpos = grid.faces(axis).ijk(f);
        println!(
            "step {k:3}: body v {:.2e} of {:.2e}; particle {p} {:.2e} of {:.2e} (at {:.4?}, body sdf/dx {:+.3}); φ {:.2e} of {:.2e} at {:?} (φ/dx {:+.3}); u {:.2e} of {:.2e} at face {:?} of axis {axis}",
            (va - 2.0 * vb + vc).length(),
            (va - vc).length(),
            dp,
            first,
            at.to_array(),
            body.sdf(at) / grid.dx,
            dphi,
            phi_first,
            grid.cells().ijk(cell),
            fb[cell] / grid.dx,
            du,
            u_first,
            fpos,
        );
        // The body's face fractions where each run has it after the step.
        let fr: Vec<_> = s.iter().map(|sim| sim.bodies()[0].face_fractions(&grid)).collect();
        let mut worst = (0.0f64, 0usize, 0usize, 0.0f64);
        for d in 0..3 {
            let look = |k: usize, f: usize| {
                fr[k].faces[d]
                    .binary_search_by_key(&f, |e| e.0)
                    .map_or(0.0, |i| fr[k].faces[d][i].1)
            };
            for &(f, beta) in &fr[1].faces[d] {
                let dd = (look(0, f) - 2.0 * beta + look(2, f)).abs();
                if dd > worst.0 {
                    worst = (dd, d, f, beta);
                }
            }
        }
        println!(
            "  fractions: {:.2e} at face {:?} of axis {} (β {:.4})",
            worst.0,
            grid.faces(worst.1).ijk(worst.2),
            worst.1,
            worst.3
        );
        // The step's own records: φ_L its projection read, the pressure, the particles
        // after advection (before the push), the density projection's potentials.
        let flat = |f: &dyn Fn(&StepRecord) -> Vec<f64>| -> String {
            let v: Vec<Vec<f64>> = recs.iter().map(f).collect();
            if v[0].len() != v[1].len() || v[1].len() != v[2].len() {
                return format!("lengths {} {} {}", v[0].len(), v[1].len(), v[2].len());
            }
            let (i, dd, d1) = differences(&v[0], &v[1], &v[2]);
            format!("{dd:.2e} of {d1:.2e} at {i}")
        };
        let moved = |r: &StepRecord| -> Vec<f64> {
            r.particles
                .as_ref()
                .map_or(Vec::new(), |p| p.moved.iter().flat_map(|x| x.to_array()).collect())
        };
        let dens = |r: &StepRecord| -> Vec<f64> {
            r.particles.as_ref().map_or(Vec::new(), |p| p.density.concat())
        };
        println!(
            "  taped: φ {}; p {}; moved {}; density q {}",
            flat(&|r| r.phi.clone()),
            flat(&|r| r.p.clone()),
            flat(&moved),
            flat(&dens)
        );
    }
    Ok(())
}

/// Over three equally long series: where the second difference |a − 2b + c| is largest,
/// that difference, and the largest first difference |a − c|.
fn differences(a: &[f64], b: &[f64], c: &[f64]) -> (usize, f64, f64) {
    let (i, second) = largest((0..b.len()).map(|i| (a[i] - 2.0 * b[i] + c[i]).abs()));
    let first = largest((0..b.len()).map(|i| (a[i] - c[i]).abs())).1;
    (i, second, first)
}

/// The index and value of the largest of `x` (the first, where several are).
fn largest(x: impl Iterator<Item = f64>) -> (usize, f64) {
    x.enumerate().fold((0, f64::NEG_INFINITY), |m, (i, v)| if v > m.1 { (i, v) } else { m })
}
