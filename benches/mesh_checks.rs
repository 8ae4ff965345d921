//! The checks a loaded OBJ mesh passes (closed, one fan a vertex, no self-intersection,
//! nested shells alternating), on the meshes that made them quadratic: a long thin closed
//! tube along z (every triangle's x-range overlaps every other's, so a sweep along x tests
//! all pairs), 4,000 disjoint small cubes (a winding number per shell pair), and a
//! million-triangle sphere. Each mesh is written as an OBJ file with a scene that holds it as
//! a body in a small tank (for timing the whole `diffluid run`), then `load_obj` is timed.
//!
//! `cargo bench --bench mesh_checks` runs every case; `MESH_BENCH_CASES=tube_200k,cubes_4000`
//! picks some, `MESH_BENCH_RUNS` sets the repetitions (default 3, the median is printed) and
//! `MESH_BENCH_DIR` keeps the files in that folder.

use diffluid::geometry::mesh::load_obj;
use std::fmt::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A closed tube of radius `r` along z from `z0` to `z1`, `k` sides, `n` segments, centred
/// on (cx, cy): 2kn + 2k triangles, counter-clockwise seen from outside.
fn tube(k: usize, n: usize, r: f64, (cx, cy): (f64, f64), (z0, z1): (f64, f64)) -> String {
    let mut obj = String::new();
    for s in 0..=n {
        let z = z0 + (z1 - z0) * s as f64 / n as f64;
        for a in 0..k {
            let t = std::f64::consts::TAU * a as f64 / k as f64;
            writeln!(obj, "v {} {} {}", cx + r * t.cos(), cy + r * t.sin(), z).unwrap();
        }
    }
    let ring = |s: usize, a: usize| 1 + s * k + a % k;
    let (bottom, top) = ((n + 1) * k + 1, (n + 1) * k + 2);
    writeln!(obj, "v {cx} {cy} {z0}\nv {cx} {cy} {z1}").unwrap();
    for s in 0..n {
        for a in 0..k {
            let (p, q, r, t) = (ring(s, a), ring(s, a + 1), ring(s + 1, a + 1), ring(s + 1, a));
            writeln!(obj, "f {p} {q} {r}\nf {p} {r} {t}").unwrap();
        }
    }
    for a in 0..k {
        writeln!(obj, "f {bottom} {} {}", ring(0, a + 1), ring(0, a)).unwrap();
        writeln!(obj, "f {top} {} {}", ring(n, a), ring(n, a + 1)).unwrap();
    }
    obj
}

/// `nx·ny·nz` disjoint cubes of side `side` on a lattice of pitch `pitch` from `origin`.
fn cubes(n: [usize; 3], side: f64, pitch: f64, origin: [f64; 3]) -> String {
    let mut obj = String::new();
    let quads =
        [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
    let mut first = 1;
    for i in 0..n[0] {
        for j in 0..n[1] {
            for l in 0..n[2] {
                let lo = [i, j, l].map(|c| c as f64 * pitch);
                for c in 0..8 {
                    let at = |axis: usize, bit: usize| {
                        origin[axis] + lo[axis] + if c & bit == 0 { 0.0 } else { side }
                    };
                    writeln!(obj, "v {} {} {}", at(0, 1), at(1, 2), at(2, 4)).unwrap();
                }
                for q in quads {
                    let [a, b, c, d] = q.map(|v| v + first);
                    writeln!(obj, "f {a} {b} {c}\nf {a} {c} {d}").unwrap();
                }
                first += 8;
            }
        }
    }
    obj
}

/// A UV sphere of radius `r` at `centre`: `lon` meridians, `lat` bands, 2·lon·(lat − 1)
/// triangles.
fn sphere(lon: usize, lat: usize, r: f64, centre: [f64; 3]) -> String {
    let mut obj = String::new();
    for b in 1..lat {
        let phi = std::f64::consts::PI * b as f64 / lat as f64;
        for a in 0..lon {
            let t = std::f64::consts::TAU * a as f64 / lon as f64;
            let (x, y, z) = (phi.sin() * t.cos(), phi.cos(), phi.sin() * t.sin());
            writeln!(obj, "v {} {} {}", centre[0] + r * x, centre[1] + r * y, centre[2] + r * z)
                .unwrap();
        }
    }
    let ring = |b: usize, a: usize| 1 + (b - 1) * lon + a % lon;
    let (north, south) = ((lat - 1) * lon + 1, (lat - 1) * lon + 2);
    let [cx, cy, cz] = centre;
    writeln!(obj, "v {cx} {} {cz}\nv {cx} {} {cz}", cy + r, cy - r).unwrap();
    for b in 1..lat - 1 {
        for a in 0..lon {
            let (p, q, s, t) = (ring(b, a), ring(b, a + 1), ring(b + 1, a + 1), ring(b + 1, a));
            writeln!(obj, "f {p} {q} {s}\nf {p} {s} {t}").unwrap();
        }
    }
    for a in 0..lon {
        writeln!(obj, "f {north} {} {}", ring(1, a + 1), ring(1, a)).unwrap();
        writeln!(obj, "f {south} {} {}", ring(lat - 1, a), ring(lat - 1, a + 1)).unwrap();
    }
    obj
}

/// A scene of a 1 m tank at dx 0.1, a pool 0.3 m deep, and the mesh at `obj` as a fixed
/// body (its OBJ coordinates are in the tank's frame, so it sits at the origin).
fn scene(name: &str, obj: &Path) -> String {
    format!(
        "name = \"{name}\"\n[domain]\nsize = [1.0, 1.0, 1.0]\ndx = 0.1\n[time]\ndt = 0.01\n\
         steps = 1\n[fluid]\ndensity = 1000.0\ngravity = [0.0, -9.81, 0.0]\n[[liquid]]\n\
         shape = {{ kind = \"box\", min = [0.0, 0.0, 0.0], max = [1.0, 0.3, 1.0] }}\n\
         [[body]]\nname = \"mesh\"\nshape = {{ kind = \"mesh\", obj = \"{}\", scale = 1.0 }}\n\
         density = 500.0\nposition = [0.0, 0.0, 0.0]\ndynamic = false\n[output]\n\
         particles = false\n",
        obj.display()
    )
}

/// A case: its name and the OBJ text it writes.
type Case = (&'static str, Box<dyn Fn() -> String>);

/// The process's CPU time so far (user and system, all threads), from /proc/self/stat in
/// clock ticks of 1/100 s; 0 where there is no /proc. On a machine shared with other work the
/// wall time grows with the load, the CPU time much less.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // The fields after the command (in parentheses, which may hold spaces), from the state:
    // utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn main() {
    let cases: Vec<Case> = vec![
        ("tube_200k", Box::new(|| tube(8, 12_499, 0.05, (0.5, 0.5), (0.1, 0.9)))),
        ("cubes_4000", Box::new(|| cubes([20, 10, 20], 0.02, 0.04, [0.1, 0.45, 0.1]))),
        ("tube_1m", Box::new(|| tube(8, 62_499, 0.05, (0.5, 0.5), (0.1, 0.9)))),
        ("sphere_1m", Box::new(|| sphere(1000, 500, 0.2, [0.5, 0.5, 0.5]))),
    ];
    let pick = std::env::var("MESH_BENCH_CASES").ok();
    let runs: usize =
        std::env::var("MESH_BENCH_RUNS").ok().and_then(|s| s.parse().ok()).unwrap_or(3);
    let (dir, keep) = match std::env::var("MESH_BENCH_DIR") {
        Ok(d) => (PathBuf::from(d), true),
        Err(_) => (
            std::env::temp_dir().join(format!("diffluid-mesh-bench-{}", std::process::id())),
            false,
        ),
    };
    std::fs::create_dir_all(&dir).unwrap();
    for (name, make) in &cases {
        if pick.as_ref().is_some_and(|p| !p.split(',').any(|c| c == *name)) {
            continue;
        }
        let obj = dir.join(format!("{name}.obj"));
        std::fs::write(&obj, make()).unwrap();
        std::fs::write(dir.join(format!("{name}.toml")), scene(name, &obj)).unwrap();
        let (mut wall, mut cpu) = (Vec::new(), Vec::new());
        let mut triangles = 0;
        for _ in 0..runs {
            let (start, cpu0) = (Instant::now(), cpu_seconds());
            let shape = load_obj(&obj, 1.0).unwrap_or_else(|e| panic!("{name}: {e}"));
            wall.push(start.elapsed().as_secs_f64());
            cpu.push(cpu_seconds() - cpu0);
            triangles = shape.as_trimesh().map_or(0, |m| m.indices().len());
        }
        wall.sort_by(f64::total_cmp);
        cpu.sort_by(f64::total_cmp);
        println!(
            "{name}: {triangles} triangles, load_obj median {:.3} s wall (min {:.3}, max {:.3}), \
             {:.3} s CPU, over {runs} runs",
            wall[runs / 2],
            wall[0],
            wall[runs - 1],
            cpu[runs / 2]
        );
    }
    if !keep {
        std::fs::remove_dir_all(&dir).ok();
    }
}
