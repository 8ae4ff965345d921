//! `diffluid render`: a run's surface and body frames drawn as a GIF or one PNG, the picture's
//! size checked against what memory holds.

use crate::error::{Error, Result};
use crate::io::plot::{self, Frame};
use crate::io::render::View;
use crate::math::Vec3;
use std::path::Path;

/// The narrowest and the widest picture [`render_run`] draws, pixels a side (a frame is held
/// in memory at 3 bytes a pixel: 4096 x 4096 is 50 MB).
pub const MIN_PICTURE_SIDE: u32 = 64;
/// See [`MIN_PICTURE_SIDE`].
pub const MAX_PICTURE_SIDE: u32 = 4096;

/// What [`render_run`] draws.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RenderRequest {
    /// One frame (by step) as a PNG, instead of every frame as a GIF.
    pub frame: Option<usize>,
    /// The file to write [default: DIR/render.gif, or DIR/render_NNNN.png for one frame].
    pub out: Option<std::path::PathBuf>,
    /// The picture's width in pixels; the height follows the tank's extent in the view.
    pub width: u32,
    /// Seen from the side (x–y) or from above (x–z).
    pub view: View,
}

/// Draws a run's frames (a folder `diffluid run` wrote with `output.surface = true`): the
/// liquid's surface from `surface/NNNN.ply` (or `.obj`) and every body from
/// `bodies/<name>_NNNN.ply`, seen from the side or from above, as an animated GIF or one PNG. Returns the
/// file written and the number of frames drawn.
pub fn render_run(dir: &Path, request: &RenderRequest) -> Result<(std::path::PathBuf, usize)> {
    let fail = |path: &Path, message: String| Error::Read { path: path.to_path_buf(), message };
    let bad = |key: &str, message: String| Error::InvalidSettings { key: key.into(), message };
    if !(MIN_PICTURE_SIDE..=MAX_PICTURE_SIDE).contains(&request.width) {
        return Err(bad(
            "width",
            format!(
                "must be {MIN_PICTURE_SIDE} to {MAX_PICTURE_SIDE} pixels, got {}",
                request.width
            ),
        ));
    }
    let out = match (&request.out, request.frame) {
        (Some(p), _) => p.clone(),
        (None, Some(n)) => dir.join(format!("render_{n:04}.png")),
        (None, None) => dir.join("render.gif"),
    };
    let (what, ext) = match request.frame {
        Some(_) => ("one frame is drawn as a PNG", "png"),
        None => ("the frames are drawn as a GIF", "gif"),
    };
    let given = out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if given.as_deref() != Some(ext) {
        return Err(bad(
            "out",
            format!("{what}: give a path ending in .{ext}, got {}", out.display()),
        ));
    }
    let summary_path = dir.join("summary.json");
    let RunSummary { name, domain, dt } = RunSummary::read(&summary_path)?;
    // The surface frames by step.
    let surface = dir.join("surface");
    let mut frames: Vec<(usize, std::path::PathBuf)> = std::fs::read_dir(&surface)
        .map_err(|e| {
            fail(&surface, format!("{e}: the run wrote no surface (set output.surface = true)"))
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| {
            let ext = p.extension()?.to_str()?;
            let n = p.file_stem()?.to_str()?.parse().ok()?;
            (ext == "ply" || ext == "obj").then_some((n, p))
        })
        .collect();
    frames.sort();
    if let Some(n) = request.frame {
        frames.retain(|(m, _)| *m == n);
        if frames.is_empty() {
            return Err(fail(&surface, format!("no surface frame for step {n}")));
        }
    }
    if frames.is_empty() {
        return Err(fail(&surface, "no surface frames (NNNN.ply or NNNN.obj)".into()));
    }
    // A summary can describe a tank of any shape: its picture must still fit in memory.
    picture_height(domain, request.view, request.width.max(64))?;
    let body_files: Vec<std::path::PathBuf> = std::fs::read_dir(dir.join("bodies"))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    let mut drawn = Vec::with_capacity(frames.len());
    for (n, path) in &frames {
        let suffix = format!("_{n:04}.ply");
        let mut bodies = Vec::new();
        for b in body_files.iter().filter(|p| {
            p.file_name().and_then(|f| f.to_str()).is_some_and(|f| f.ends_with(&suffix))
        }) {
            bodies.push(crate::io::output::read_mesh(b)?);
        }
        drawn.push(Frame {
            liquid: crate::io::output::read_mesh(path)?,
            bodies,
            label: format!("{name}, step {n}, t = {:.2} s", *n as f64 * dt),
        });
    }
    let width = request.width;
    // The plot's margins and caption take about 60 pixels around the tank's side.
    let up = request.view.extent(domain).1;
    let height = ((width as f64 - 45.0) * up / domain.x + 60.0).round();
    if !(height >= MIN_PICTURE_SIDE as f64 && height <= MAX_PICTURE_SIDE as f64) {
        return Err(bad(
            "width",
            format!(
                "the picture would be {width} x {height} pixels (the tank is {:.3} x {up:.3} m \
                 in this view): each side must be {MIN_PICTURE_SIDE} to {MAX_PICTURE_SIDE}",
                domain.x
            ),
        ));
    }
    let height = height as u32;
    match request.frame {
        Some(_) => plot::frame_png(&out, domain, &drawn[0], request.view, (width, height))?,
        None => {
            // Real time when the frames allow it, between 20 ms and 0.2 s a frame.
            let step = frames.get(1).map_or(1, |f| f.0 - frames[0].0).max(1);
            let delay = (1e3 * dt * step as f64).clamp(20.0, 200.0) as u32;
            plot::animation_gif(&out, domain, &drawn, request.view, (width, height), delay)?
        }
    }
    Ok((out, drawn.len()))
}

/// The tallest picture `render` draws, in pixels: a tank much taller than wide (or deep, from
/// above) would otherwise ask for a picture of any size.
pub const MAX_PICTURE_HEIGHT: u32 = 8192;

/// What `render` reads of a run's `summary.json`: the scene's name, the tank's extent and
/// the step.
struct RunSummary {
    name: String,
    domain: Vec3,
    dt: f64,
}

impl RunSummary {
    /// Reads and checks `summary.json`: three whole positive cell counts, a positive dx and dt,
    /// a finite tank.
    fn read(path: &Path) -> Result<RunSummary> {
        let fail = |message: String| Error::Read { path: path.to_path_buf(), message };
        let text = crate::math::input::read_text(path)
            .map_err(|e| fail(format!("{e} (not a folder `diffluid run` wrote?)")))?;
        let summary: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| fail(e.to_string()))?;
        let grid: Option<Vec<u64>> = summary["grid"]
            .as_array()
            .and_then(|a| a.iter().map(serde_json::Value::as_u64).collect());
        let (Some(dx), Some(dt), Some(grid)) =
            (summary["dx"].as_f64(), summary["dt"].as_f64(), grid)
        else {
            return Err(fail("no grid, dx and dt".into()));
        };
        let [nx, ny, nz] = grid[..] else {
            return Err(fail(format!("grid {grid:?}: three cell counts expected")));
        };
        if grid.contains(&0) {
            return Err(fail(format!("grid {grid:?}: every axis needs at least one cell")));
        }
        if !(dx.is_finite() && dx > 0.0 && dt.is_finite() && dt > 0.0) {
            return Err(fail(format!("dx {dx} and dt {dt} must be positive")));
        }
        let domain = Vec3::new(nx as f64, ny as f64, nz as f64) * dx;
        if !domain.is_finite() {
            return Err(fail(format!("a tank of {grid:?} cells of {dx} m is not finite")));
        }
        let name = summary["scene"].as_str().unwrap_or("run").to_string();
        Ok(RunSummary { name, domain, dt })
    }
}

/// The height of a picture `width` pixels wide of a tank of extent `domain` seen from
/// `view`: the tank's aspect in the view, and about 60 pixels for the plot's margins and
/// caption. At most [`MAX_PICTURE_HEIGHT`].
fn picture_height(domain: Vec3, view: View, width: u32) -> Result<u32> {
    let (right, up) = view.extent(domain);
    let height = ((width as f64 - 45.0) * up / right + 60.0).round();
    if height.is_nan() || height > MAX_PICTURE_HEIGHT as f64 {
        return Err(Error::InvalidSettings {
            key: "render".into(),
            message: format!(
                "the tank is {:.0} times taller than wide in this view: a picture {width} \
                 pixels wide would be {height} high (at most {MAX_PICTURE_HEIGHT}); give a \
                 smaller --width or the other --view",
                up / right
            ),
        });
    }
    Ok(height as u32)
}
