//! ParaView frames through vtkio: per frame the liquid's marker particles (PolyData points
//! with the grid velocity there), each body's surface (PolyData triangles with the rigid
//! velocity at each vertex) and the grid (ImageData with cell pressure, cell-centred velocity
//! and the liquid signed distance), plus one `.pvd` collection per series listing the frames
//! with their times, so ParaView plays them as an animation.
//!
//! Files are VTK XML (`.vtp`, `.vti`) with inline binary arrays in f64, written atomically.

use crate::error::{Error, Result};
use crate::math::Vec3;
use crate::world::Simulation;
use std::path::{Path, PathBuf};
use vtkio::model::{
    Attribute, Attributes, ByteOrder, DataSet, Extent, ImageDataPiece, Piece, PolyDataPiece,
    Version, VertexNumbers, Vtk,
};

/// A series of frames being written to one folder.
#[derive(Debug)]
pub struct VtkSeries {
    dir: PathBuf,
    /// The run's name, in each file's title.
    name: String,
    /// Per series name ("liquid", "grid", "body_`name`"): (time, file name) of each frame.
    series: Vec<(String, Vec<(f64, String)>)>,
}

fn flat(points: impl Iterator<Item = Vec3>) -> Vec<f64> {
    points.flat_map(|p| p.to_array()).collect()
}

fn vtk_err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Write { path: path.to_path_buf(), source: std::io::Error::other(format!("VTK: {e}")) }
}

/// Writes a data set as VTK XML, atomically.
fn write_vtk(path: &Path, title: &str, data: DataSet) -> Result<()> {
    let vtk = Vtk {
        version: Version::new_xml(1, 0),
        title: title.into(),
        byte_order: ByteOrder::LittleEndian,
        data,
        file_path: None,
    };
    let mut buf = Vec::new();
    vtk.write_xml(&mut buf).map_err(|e| vtk_err(path, e))?;
    crate::io::output::write_atomic(path, &buf)
}

/// The liquid's marker particles with the grid velocity at each, as PolyData vertices.
pub fn particles_data(sim: &Simulation) -> DataSet {
    let grid = sim.grid();
    let n = sim.particles.len() as u64;
    let velocity = flat(sim.particles.iter().map(|p| sim.u.velocity(grid, *p)));
    DataSet::inline(PolyDataPiece {
        points: flat(sim.particles.iter().copied()).into(),
        verts: Some(VertexNumbers::XML {
            connectivity: (0..n).collect(),
            offsets: (1..=n).collect(),
        }),
        data: Attributes {
            point: vec![Attribute::vectors("velocity").with_data(velocity)],
            cell: Vec::new(),
        },
        ..Default::default()
    })
}

/// Body `b`'s surface in world space as PolyData triangles, with the rigid velocity at each
/// vertex.
pub fn body_data(sim: &Simulation, b: usize) -> DataSet {
    let body = &sim.bodies()[b];
    let mesh = crate::geometry::mesh::placed_surface(&body.shape, &body.pose());
    let velocity = flat(mesh.vertices.iter().map(|p| body.velocity_at(*p)));
    triangles_data(
        &mesh.vertices,
        &mesh.triangles,
        vec![Attribute::vectors("velocity").with_data(velocity)],
    )
}

/// A triangle mesh as PolyData, with `point` attributes.
fn triangles_data(vertices: &[Vec3], triangles: &[[u32; 3]], point: Vec<Attribute>) -> DataSet {
    DataSet::inline(PolyDataPiece {
        points: flat(vertices.iter().copied()).into(),
        polys: Some(VertexNumbers::XML {
            connectivity: triangles.iter().flat_map(|t| t.map(u64::from)).collect(),
            offsets: (1..=triangles.len() as u64).map(|c| 3 * c).collect(),
        }),
        data: Attributes { point, cell: Vec::new() },
        ..Default::default()
    })
}

/// The grid as ImageData (one VTK cell per grid cell): pressure (Pa, zero outside the
/// liquid), velocity at cell centres (the mean of each axis's two faces) and the liquid
/// signed distance, as cell data.
pub fn grid_data(sim: &Simulation) -> DataSet {
    let grid = sim.grid();
    let cells = grid.cells();
    let mut velocity = Vec::with_capacity(3 * cells.len());
    for idx in 0..cells.len() {
        let [i, j, k] = cells.ijk(idx);
        for a in 0..3 {
            let faces = grid.faces(a);
            let mut hi = [i, j, k];
            hi[a] += 1;
            let (lo, hi) = (faces.index(i, j, k), faces.index(hi[0], hi[1], hi[2]));
            velocity.push(0.5 * (sim.u.c[a][lo] + sim.u.c[a][hi]));
        }
    }
    let [nx, ny, nz] = grid.n.map(|n| n as i32);
    let extent = Extent::Ranges([0..=nx, 0..=ny, 0..=nz]);
    DataSet::ImageData {
        extent: extent.clone(),
        origin: [0.0; 3],
        spacing: [grid.dx as f32; 3],
        meta: None,
        pieces: vec![Piece::Inline(Box::new(ImageDataPiece {
            extent,
            data: Attributes {
                point: Vec::new(),
                cell: vec![
                    Attribute::scalars("pressure", 1).with_data(sim.pressure().to_vec()),
                    Attribute::vectors("velocity").with_data(velocity),
                    Attribute::scalars("liquid_phi", 1).with_data(sim.liquid_phi().to_vec()),
                ],
            },
        }))],
    }
}

impl VtkSeries {
    /// A series of the run `name` written into `dir`.
    pub fn new(dir: &Path, name: &str) -> VtkSeries {
        VtkSeries { dir: dir.to_path_buf(), name: name.into(), series: Vec::new() }
    }

    fn add(&mut self, name: &str, time: f64, file: String) {
        match self.series.iter_mut().find(|(n, _)| n == name) {
            Some((_, frames)) => frames.push((time, file)),
            None => self.series.push((name.into(), vec![(time, file)])),
        }
    }

    /// Writes frame `n` of `sim` (particles, bodies, grid) and rewrites the `.pvd` files, so
    /// a run that fails part-way still leaves a playable series.
    pub fn write_frame(&mut self, sim: &Simulation, n: usize) -> Result<()> {
        crate::io::output::check_body_names(sim.bodies().iter().map(|b| b.name.as_str()))?;
        let time = sim.time();
        let title = format!("diffluid {} frame {n} t = {time} s", self.name);
        let mut files = vec![
            ("liquid".to_string(), format!("liquid_{n:04}.vtp"), particles_data(sim)),
            ("grid".to_string(), format!("grid_{n:04}.vti"), grid_data(sim)),
        ];
        for (b, body) in sim.bodies().iter().enumerate() {
            let name = format!("body_{}", body.name);
            files.push((name.clone(), format!("{name}_{n:04}.vtp"), body_data(sim, b)));
        }
        for (series, file, data) in files {
            write_vtk(&self.dir.join(&file), &title, data)?;
            self.add(&series, time, file);
        }
        self.write_collections()
    }

    /// Writes the liquid's surface mesh of frame `n` at `time` as PolyData triangles (series
    /// "surface") and rewrites the `.pvd` files.
    pub fn write_surface(
        &mut self,
        time: f64,
        n: usize,
        vertices: &[Vec3],
        triangles: &[[u32; 3]],
    ) -> Result<()> {
        let title = format!("diffluid {} liquid surface frame {n} t = {time} s", self.name);
        let file = format!("surface_{n:04}.vtp");
        write_vtk(&self.dir.join(&file), &title, triangles_data(vertices, triangles, Vec::new()))?;
        self.add("surface", time, file);
        self.write_collections()
    }

    /// One `<series>.pvd` per series: a VTK Collection of its frames with their times.
    fn write_collections(&self) -> Result<()> {
        for (name, frames) in &self.series {
            let mut xml = String::from(
                "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\" \
                 byte_order=\"LittleEndian\">\n  <Collection>\n",
            );
            for (t, file) in frames {
                // A body's name is checked to be safe in a file name and in XML; escaped all
                // the same, so no name can make the collection invalid XML.
                let file = crate::io::output::xml_escape(file);
                xml.push_str(&format!(
                    "    <DataSet timestep=\"{t}\" group=\"\" part=\"0\" file=\"{file}\"/>\n"
                ));
            }
            xml.push_str("  </Collection>\n</VTKFile>\n");
            crate::io::output::write_atomic(&self.dir.join(format!("{name}.pvd")), xml.as_bytes())?;
        }
        Ok(())
    }
}
