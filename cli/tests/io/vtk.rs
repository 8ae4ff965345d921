//! ParaView frames: what `--vtk` writes parses back with vtkio and holds what the simulation
//! had: one vertex cell per liquid particle, the body's surface triangles, one grid cell per
//! simulation cell with its pressure, and `.pvd` collections listing every frame with its time.

use crate::common::EXE;
use diffluid::io::vtk::VtkSeries;
use diffluid::Scene;
use std::path::Path;
use std::process::Command;
use vtkio::model::{Attribute, DataSet, Piece, PolyDataPiece, Vtk};

fn poly(path: &Path) -> PolyDataPiece {
    let vtk = Vtk::import(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    match vtk.data {
        DataSet::PolyData { mut pieces, .. } => match pieces.remove(0) {
            Piece::Inline(p) => *p,
            _ => panic!("not inline"),
        },
        other => panic!("{}: not PolyData: {other:?}", path.display()),
    }
}

fn array_len(attrs: &[Attribute], name: &str) -> usize {
    attrs
        .iter()
        .find_map(|a| match a {
            Attribute::DataArray(d) if d.name == name => Some(d.data.len()),
            _ => None,
        })
        .unwrap_or_else(|| panic!("no array {name}"))
}

#[test]
fn frames_parse_back_with_the_simulations_counts() {
    let dir = std::env::temp_dir().join(format!("diffluid-vtk-{}", std::process::id()));
    let mut sim = Scene::builtin("dam_break_ball").unwrap().build().unwrap();
    let mut series = VtkSeries::new(&dir, "dam_break_ball");
    series.write_frame(&sim, 0).unwrap();
    sim.step().unwrap();
    series.write_frame(&sim, 1).unwrap();

    let liquid = poly(&dir.join("liquid_0001.vtp"));
    let n = sim.particles().len();
    assert!(n > 0);
    assert_eq!(liquid.num_points(), n);
    assert_eq!(liquid.verts.as_ref().unwrap().num_cells(), n);
    assert_eq!(array_len(&liquid.data.point, "velocity"), 3 * n);

    let ball = poly(&dir.join("body_ball_0001.vtp"));
    let (verts, tris) = diffluid::geometry::mesh::surface_mesh(&sim.bodies()[0].shape);
    assert_eq!(ball.num_points(), verts.len());
    assert_eq!(ball.polys.as_ref().unwrap().num_cells(), tris.len());
    // The points are the body's surface where it is now: all at the radius from its centre.
    let pts: Vec<f64> = ball.points.cast_into().unwrap();
    let c = sim.bodies()[0].x.to_array();
    for p in pts.chunks(3) {
        let r = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
        assert!((r - 0.2).abs() < 1e-9, "vertex at {r} from the centre");
    }

    let grid = Vtk::import(dir.join("grid_0001.vti")).unwrap();
    let cells = sim.grid().num_cells();
    match grid.data {
        DataSet::ImageData { extent, spacing, pieces, .. } => {
            assert_eq!(extent.num_cells() as usize, cells);
            assert_eq!(spacing, [0.1f32; 3]);
            let Piece::Inline(p) = &pieces[0] else { panic!("not inline") };
            assert_eq!(array_len(&p.data.cell, "pressure"), cells);
            assert_eq!(array_len(&p.data.cell, "velocity"), 3 * cells);
            let pressure: Vec<f64> = match &p.data.cell[0] {
                Attribute::DataArray(d) => d.data.cast_into().unwrap(),
                _ => panic!("pressure is not a data array"),
            };
            assert_eq!(pressure, sim.pressure(), "pressure read back bit for bit");
        }
        other => panic!("not ImageData: {other:?}"),
    }

    let pvd = std::fs::read_to_string(dir.join("liquid.pvd")).unwrap();
    assert!(pvd.contains("type=\"Collection\""));
    assert!(pvd.contains("timestep=\"0\"") && pvd.contains("file=\"liquid_0000.vtp\""));
    assert!(pvd.contains("timestep=\"0.05\"") && pvd.contains("file=\"liquid_0001.vtp\""));
    std::fs::remove_dir_all(&dir).ok();
}

/// `run --vtk` writes a frame every output.every steps; `optimize --vtk` writes every step of
/// the optimised run.
#[test]
fn run_and_optimize_write_frames_on_request() {
    let dir = std::env::temp_dir().join(format!("diffluid-vtk-cli-{}", std::process::id()));
    let bin = EXE;
    let run = Command::new(bin)
        .args(["run", "dam_break_ball", "--steps", "2", "--vtk", "--quiet", "--out"])
        .arg(dir.join("run"))
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let pvd = std::fs::read_to_string(dir.join("run/vtk/body_ball.pvd")).unwrap();
    assert_eq!(pvd.matches("<DataSet ").count(), 3, "{pvd}");
    assert!(poly(&dir.join("run/vtk/body_ball_0002.vtp")).num_points() > 0);

    let opt = Command::new(bin)
        .args(["optimize", "recover_box", "--epochs", "1", "--vtk", "--quiet", "--out"])
        .arg(dir.join("opt"))
        .output()
        .unwrap();
    assert!(opt.status.success(), "{}", String::from_utf8_lossy(&opt.stderr));
    let steps = Scene::builtin("recover_box").unwrap().time.steps;
    let pvd = std::fs::read_to_string(dir.join("opt/vtk/grid.pvd")).unwrap();
    assert_eq!(pvd.matches("<DataSet ").count(), steps + 1);
    assert!(Vtk::import(dir.join(format!("opt/vtk/grid_{steps:04}.vti"))).is_ok());
    std::fs::remove_dir_all(&dir).ok();
}
