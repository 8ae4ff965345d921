//! Pictures of an optimisation: the loss curve, the body's path over the liquid, and an
//! animated GIF of the liquid's shaded surface with the bodies in it (a run's frames, too).
//! Text is drawn with the embedded DejaVu Sans (no system fonts needed).

use crate::error::{Error, Result};
use crate::io::render::{render, Picture, TriangleMesh, View};
use crate::math::Vec3;
use plotters::element::BitMapElement;
use plotters::prelude::*;
use std::path::Path;

static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

fn font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
            .unwrap_or_else(|_| panic!("the embedded font is valid"));
    });
}

fn err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Write { path: path.to_path_buf(), source: std::io::Error::other(e.to_string()) }
}

/// The loss (and the gradient norm) per epoch on a log axis, as a PNG.
pub fn loss_plot(path: &Path, loss: &[f64], grad_norm: &[f64]) -> Result<()> {
    crate::io::output::write_through(path, |at| loss_plot_at(at, path, loss, grad_norm))
}

fn loss_plot_at(at: &Path, path: &Path, loss: &[f64], grad_norm: &[f64]) -> Result<()> {
    font();
    if loss.is_empty() {
        return Err(err(path, "no epochs to plot"));
    }
    let pos: Vec<f64> =
        loss.iter().chain(grad_norm).copied().filter(|x| *x > 0.0 && x.is_finite()).collect();
    let (lo, hi) = pos.iter().fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    let (lo, hi) = if lo <= hi { (lo * 0.5, hi * 2.0) } else { (1e-12, 1.0) };
    let root = BitMapBackend::new(at, (900, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let n = loss.len().max(2) - 1;
    let mut chart = ChartBuilder::on(&root)
        .caption("loss", ("sans-serif", 24))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0..n, (lo..hi).log_scale())
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .x_desc("epoch")
        .y_desc("loss, |gradient|")
        .draw()
        .map_err(|e| err(path, e))?;
    let series = |v: &[f64]| -> Vec<(usize, f64)> {
        v.iter()
            .enumerate()
            .filter(|(_, x)| **x > 0.0 && x.is_finite())
            .map(|(i, x)| (i, *x))
            .collect()
    };
    chart
        .draw_series(LineSeries::new(series(loss), BLUE.stroke_width(2)))
        .map_err(|e| err(path, e))?
        .label("loss")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .draw_series(LineSeries::new(series(grad_norm), RED.mix(0.7)))
        .map_err(|e| err(path, e))?
        .label("gradient norm")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.mix(0.7)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(path, e))?;
    root.present().map_err(|e| err(path, e))
}

/// A body's path, with a label.
#[derive(Clone, Debug)]
pub struct Track {
    /// Legend label.
    pub label: String,
    /// Centre of mass per step.
    pub points: Vec<Vec3>,
}

/// Draws `picture` seen from `view` under a chart whose axes span the domain in that view.
fn draw_picture<DB: DrawingBackend>(
    chart: &mut ChartContext<
        '_,
        DB,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
    picture: &Picture,
    view: View,
    path: &Path,
) -> Result<()> {
    let (w, h) = chart.plotting_area().dim_in_pixel();
    let image = render(picture, view, w, h);
    let top = view.extent(picture.domain).1;
    let element = BitMapElement::with_owned_buffer((0.0, top), (w, h), image.rgb)
        .expect("the image fits its size");
    chart.draw_series(std::iter::once(element)).map_err(|e| err(path, e))?;
    Ok(())
}

/// The liquid's colour in legends.
const WATER: RGBColor = RGBColor(100, 150, 215);

/// Side (x–y) and top (x–z) views of body paths over the liquid's shaded surface (and the
/// bodies) at one moment, `liquid` with its legend label, as a PNG.
pub fn trajectory_plot(
    path: &Path,
    domain: Vec3,
    tracks: &[Track],
    target: Option<Vec3>,
    liquid: Option<(&str, &Picture)>,
) -> Result<()> {
    crate::io::output::write_through(path, |at| {
        trajectory_plot_at(at, path, domain, tracks, target, liquid)
    })
}

fn trajectory_plot_at(
    at: &Path,
    path: &Path,
    domain: Vec3,
    tracks: &[Track],
    target: Option<Vec3>,
    liquid: Option<(&str, &Picture)>,
) -> Result<()> {
    font();
    let root = BitMapBackend::new(at, (1200, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let panels = root.split_evenly((1, 2));
    let colours = [BLUE, RED, GREEN, MAGENTA, BLACK];
    for (panel, (title, b, view)) in panels
        .iter()
        .zip([("side view (x–y)", 1usize, View::Side), ("top view (x–z)", 2usize, View::Top)])
    {
        let pick = |v: Vec3| (v.x, v.to_array()[b]);
        let mut chart = ChartBuilder::on(panel)
            .caption(title, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(45)
            .build_cartesian_2d(0.0..domain.x, 0.0..domain.to_array()[b])
            .map_err(|e| err(path, e))?;
        if let Some((label, picture)) = liquid {
            draw_picture(&mut chart, picture, view, path)?;
            chart
                .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
                .map_err(|e| err(path, e))?
                .label(label)
                .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], WATER.filled()));
        }
        chart
            .configure_mesh()
            .light_line_style(TRANSPARENT)
            .bold_line_style(BLACK.mix(0.12))
            .x_desc("x (m)")
            .y_desc(if b == 1 { "y (m)" } else { "z (m)" })
            .draw()
            .map_err(|e| err(path, e))?;
        for (k, t) in tracks.iter().enumerate() {
            let c = colours[k % colours.len()];
            chart
                .draw_series(LineSeries::new(t.points.iter().map(|p| pick(*p)), c.stroke_width(2)))
                .map_err(|e| err(path, e))?
                .label(t.label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                });
            if let Some(last) = t.points.last() {
                chart
                    .draw_series(std::iter::once(Circle::new(pick(*last), 5, c.filled())))
                    .map_err(|e| err(path, e))?;
            }
        }
        if let Some(tg) = target {
            chart
                .draw_series(std::iter::once(Cross::new(pick(tg), 8, BLACK.stroke_width(2))))
                .map_err(|e| err(path, e))?
                .label("target")
                .legend(|(x, y)| Cross::new((x + 10, y), 5, BLACK));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(path, e))?;
    }
    root.present().map_err(|e| err(path, e))
}

/// One frame of an animation: the liquid's surface and the bodies', in world coordinates.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The liquid's surface.
    pub liquid: TriangleMesh,
    /// Each body's surface.
    pub bodies: Vec<TriangleMesh>,
    /// Caption.
    pub label: String,
}

/// One frame seen from `view`, `size` pixels, as a PNG.
pub fn frame_png(
    path: &Path,
    domain: Vec3,
    frame: &Frame,
    view: View,
    size: (u32, u32),
) -> Result<()> {
    crate::io::output::write_through(path, |at| frame_png_at(at, path, domain, frame, view, size))
}

fn frame_png_at(
    at: &Path,
    path: &Path,
    domain: Vec3,
    frame: &Frame,
    view: View,
    size: (u32, u32),
) -> Result<()> {
    font();
    let root = BitMapBackend::new(at, size).into_drawing_area();
    draw_frame(&root, domain, frame, view, path)?;
    root.present().map_err(|e| err(path, e))
}

fn draw_frame<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    domain: Vec3,
    frame: &Frame,
    view: View,
    path: &Path,
) -> Result<()> {
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let up = view.extent(domain).1;
    let mut chart = ChartBuilder::on(root)
        .caption(&frame.label, ("sans-serif", 16))
        .margin(8)
        .x_label_area_size(25)
        .y_label_area_size(35)
        .build_cartesian_2d(0.0..domain.x, 0.0..up)
        .map_err(|e| err(path, e))?;
    let picture = Picture { domain, liquid: &frame.liquid, bodies: &frame.bodies };
    draw_picture(&mut chart, &picture, view, path)?;
    chart.configure_mesh().disable_mesh().draw().map_err(|e| err(path, e))?;
    Ok(())
}

/// An animated GIF of the frames seen from `view` (the side: x–y; the top: x–z), `size`
/// pixels.
pub fn animation_gif(
    path: &Path,
    domain: Vec3,
    frames: &[Frame],
    view: View,
    size: (u32, u32),
    delay_ms: u32,
) -> Result<()> {
    crate::io::output::write_through(path, |at| {
        animation_gif_at(at, path, domain, frames, view, size, delay_ms)
    })
}

/// The GIF encoder's palette sampling: 1 (every pixel, slowest) to 30 (every 30th). These
/// pictures are flat fills and lines in a few dozen colours, which every rate finds. Only
/// the first frame's palette is found; the others share it (see `animation_gif_at`).
const GIF_SPEED: i32 = 30;

fn animation_gif_at(
    at: &Path,
    path: &Path,
    domain: Vec3,
    frames: &[Frame],
    view: View,
    size: (u32, u32),
    delay_ms: u32,
) -> Result<()> {
    use rayon::prelude::*;
    font();
    if frames.is_empty() {
        return Err(err(path, "no frames"));
    }
    let (w, h) = size;
    let (gw, gh) = (
        u16::try_from(w).map_err(|_| err(path, "wider than a GIF holds"))?,
        u16::try_from(h).map_err(|_| err(path, "taller than a GIF holds"))?,
    );
    let file = std::fs::File::create(at).map_err(|e| err(path, e))?;
    let mut gif =
        gif::Encoder::new(std::io::BufWriter::new(file), gw, gh, &[]).map_err(|e| err(path, e))?;
    gif.set_repeat(gif::Repeat::Infinite).map_err(|e| err(path, e))?;
    let draw = |f: &Frame| -> Result<Vec<u8>> {
        let mut rgb = vec![0u8; 3 * w as usize * h as usize];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
            draw_frame(&root, domain, f, view, path)?;
            root.present().map_err(|e| err(path, e))?;
        }
        Ok(rgb)
    };
    let delay = u16::try_from(delay_ms.div_ceil(10)).unwrap_or(u16::MAX);
    // The first frame finds the palette (NeuQuant, when it has more than 256 colours) that
    // the others share: they hold the same liquid, bodies, axes and text, and each colour of
    // theirs takes its nearest entry (a palette a frame was most of the GIF's time).
    let mut first = gif::Frame::from_rgb_speed(gw, gh, &draw(&frames[0])?, GIF_SPEED);
    first.delay = delay;
    let palette = first.palette.clone().unwrap_or_default();
    gif.write_frame(&first).map_err(|e| err(path, e))?;
    // Drawn, mapped to the palette and LZW-compressed a few frames at a time on every
    // thread, written in order: at most a chunk of frames is held. The compression is the
    // one `write_frame` does, so the same bytes.
    let chunk = 2 * rayon::current_num_threads();
    for part in frames[1..].chunks(chunk) {
        let encoded: Vec<gif::Frame<'static>> = part
            .par_iter()
            .map(|f| -> Result<gif::Frame<'static>> {
                let indices = palette_indices(&draw(f)?, &palette);
                let mut frame = gif::Frame::from_palette_pixels(gw, gh, &indices, &palette, None);
                frame.delay = delay;
                frame.make_lzw_pre_encoded();
                Ok(frame)
            })
            .collect::<Result<_>>()?;
        for frame in &encoded {
            gif.write_lzw_pre_encoded_frame(frame).map_err(|e| err(path, e))?;
        }
    }
    let file = gif.into_inner().map_err(|e| err(path, e))?;
    file.into_inner().map_err(|e| err(path, e.error()))?.sync_all().map_err(|e| err(path, e))
}

/// Per pixel of `rgb`, the index of its colour's nearest entry of `palette` (RGB triples;
/// squared distance, the first of equals), found once for each colour.
fn palette_indices(rgb: &[u8], palette: &[u8]) -> Vec<u8> {
    let entries: Vec<[i32; 3]> =
        palette.chunks_exact(3).map(|c| [c[0], c[1], c[2]].map(i32::from)).collect();
    let nearest = |c: [u8; 3]| -> u8 {
        let d = |e: &[i32; 3]| (0..3).map(|k| (e[k] - i32::from(c[k])).pow(2)).sum::<i32>();
        let best = (0..entries.len()).min_by_key(|&i| (d(&entries[i]), i)).unwrap_or(0);
        u8::try_from(best).unwrap_or(u8::MAX)
    };
    let mut known: std::collections::HashMap<[u8; 3], u8> = std::collections::HashMap::new();
    // Runs of one colour (most of a picture) are looked up once.
    let mut last: Option<([u8; 3], u8)> = None;
    rgb.chunks_exact(3)
        .map(|p| {
            let c = [p[0], p[1], p[2]];
            match last {
                Some((l, i)) if l == c => i,
                _ => {
                    let i = *known.entry(c).or_insert_with(|| nearest(c));
                    last = Some((c, i));
                    i
                }
            }
        })
        .collect()
}

/// A labelled series of (x, y) points for the bench charts.
pub type Series = (String, Vec<(f64, f64)>);

const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

fn span(v: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (lo, hi) = v
        .filter(|x| x.is_finite() && (!log || *x > 0.0))
        .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)));
    match (lo <= hi, log) {
        (false, _) => (1e-3, 1.0),
        (true, true) => (lo / 2.0, hi * 2.0),
        (true, false) => {
            let pad = 0.05 * (hi - lo).max(1e-12);
            (lo - pad, hi + pad)
        }
    }
}

/// An axis label: plain for moderate numbers, `1e-6` style otherwise.
fn short(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 || (1e-2..1e4).contains(&a) {
        format!("{}", (x * 1e3).round() / 1e3)
    } else {
        format!("{x:.0e}")
    }
}

/// Lines with markers on log–log axes (`log_x`/`log_y` choose each axis), one per series:
/// the bench's accuracy-against-time, thin-body and cost charts.
pub fn line_chart(
    path: &Path,
    title: &str,
    (x_desc, y_desc): (&str, &str),
    (log_x, log_y): (bool, bool),
    series: &[Series],
) -> Result<()> {
    crate::io::output::write_through(path, |at| {
        line_chart_at(at, path, title, (x_desc, y_desc), (log_x, log_y), series)
    })
}

fn line_chart_at(
    at: &Path,
    path: &Path,
    title: &str,
    (x_desc, y_desc): (&str, &str),
    (log_x, log_y): (bool, bool),
    series: &[Series],
) -> Result<()> {
    font();
    let (x0, x1) = span(series.iter().flat_map(|s| s.1.iter().map(|p| p.0)), log_x);
    let (y0, y1) = span(series.iter().flat_map(|s| s.1.iter().map(|p| p.1)), log_y);
    let root = BitMapBackend::new(at, (900, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    macro_rules! builder {
        () => {
            ChartBuilder::on(&root)
                .caption(title, ("sans-serif", 22))
                .margin(15)
                .x_label_area_size(45)
                .y_label_area_size(80)
        };
    }
    macro_rules! draw {
        ($chart:expr) => {{
            let mut chart = $chart.map_err(|e| err(path, e))?;
            chart
                .configure_mesh()
                .x_desc(x_desc)
                .y_desc(y_desc)
                .x_label_formatter(&|x| short(*x))
                .y_label_formatter(&|y| short(*y))
                .draw()
                .map_err(|e| err(path, e))?;
            for (k, (label, pts)) in series.iter().enumerate() {
                let c = PALETTE[k % PALETTE.len()];
                let pts: Vec<(f64, f64)> = pts
                    .iter()
                    .copied()
                    .filter(|p| {
                        p.0.is_finite()
                            && p.1.is_finite()
                            && (!log_x || p.0 > 0.0)
                            && (!log_y || p.1 > 0.0)
                    })
                    .collect();
                chart
                    .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
                    .map_err(|e| err(path, e))?
                    .label(label.as_str())
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                    });
                chart
                    .draw_series(pts.iter().map(|p| Circle::new(*p, 4, c.filled())))
                    .map_err(|e| err(path, e))?;
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(|e| err(path, e))?;
        }};
    }
    match (log_x, log_y) {
        (true, true) => {
            draw!(builder!().build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale()))
        }
        (true, false) => draw!(builder!().build_cartesian_2d((x0..x1).log_scale(), y0..y1)),
        (false, true) => draw!(builder!().build_cartesian_2d(x0..x1, (y0..y1).log_scale())),
        (false, false) => draw!(builder!().build_cartesian_2d(x0..x1, y0..y1)),
    }
    root.present().map_err(|e| err(path, e))
}

/// One panel of the stability map: a title and (density ratio, CFL number, stable) cells.
pub type StabilityPanel = (String, Vec<(f64, f64, bool)>);

/// The stability map: one panel per coupling, density ratio (log) across, CFL number (log)
/// up, a filled green dot where the run was stable and a red cross where it was not.
pub fn stability_chart(path: &Path, panels: &[StabilityPanel]) -> Result<()> {
    crate::io::output::write_through(path, |at| stability_chart_at(at, path, panels))
}

fn stability_chart_at(at: &Path, path: &Path, panels: &[StabilityPanel]) -> Result<()> {
    font();
    let root = BitMapBackend::new(at, (500 * panels.len().max(1) as u32, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let areas = root.split_evenly((1, panels.len().max(1)));
    let (r0, r1) = span(panels.iter().flat_map(|p| p.1.iter().map(|c| c.0)), true);
    let (c0, c1) = span(panels.iter().flat_map(|p| p.1.iter().map(|c| c.1)), true);
    for (area, (name, cells)) in areas.iter().zip(panels) {
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{name} coupling"), ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(55)
            .build_cartesian_2d((r0..r1).log_scale(), (c0..c1).log_scale())
            .map_err(|e| err(path, e))?;
        chart
            .configure_mesh()
            .x_desc("density ratio ρ_body/ρ_liquid")
            .y_desc("CFL number")
            .draw()
            .map_err(|e| err(path, e))?;
        chart
            .draw_series(
                cells.iter().filter(|c| c.2).map(|c| Circle::new((c.0, c.1), 7, GREEN.filled())),
            )
            .map_err(|e| err(path, e))?;
        chart
            .draw_series(
                cells
                    .iter()
                    .filter(|c| !c.2)
                    .map(|c| Cross::new((c.0, c.1), 7, RED.stroke_width(3))),
            )
            .map_err(|e| err(path, e))?;
    }
    root.present().map_err(|e| err(path, e))
}

/// One scene's curves in the energy chart, as (time in s, energy in J) points.
#[derive(Clone, Debug, Default)]
pub struct EnergyCurves {
    /// Legend label.
    pub label: String,
    /// The total energy less its start.
    pub change: Vec<(f64, f64)>,
    /// The liquid's kinetic energy.
    pub liquid_kinetic: Vec<(f64, f64)>,
    /// The bodies' kinetic energy (empty, or all zero, for a scene without bodies: not drawn).
    pub body_kinetic: Vec<(f64, f64)>,
}

/// The energy audit's chart: above, each scene's total energy less its start against time
/// (linear, with a zero line); below, the liquid's (solid) and the bodies' (dashed) kinetic
/// energy on a log scale (zeros left out), each scene in one colour in both panels.
pub fn energy_chart(path: &Path, scenes: &[EnergyCurves]) -> Result<()> {
    crate::io::output::write_through(path, |at| energy_chart_at(at, path, scenes))
}

fn energy_chart_at(at: &Path, path: &Path, scenes: &[EnergyCurves]) -> Result<()> {
    font();
    let root = BitMapBackend::new(at, (900, 1000)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let (top, bottom) = root.split_vertically(520);
    let times = || scenes.iter().flat_map(|s| s.change.iter().map(|p| p.0));
    let t1 = times().filter(|t| t.is_finite()).fold(0.0, f64::max).max(1e-3);
    let finite = |pts: &[(f64, f64)]| -> Vec<(f64, f64)> {
        pts.iter().copied().filter(|p| p.0.is_finite() && p.1.is_finite()).collect()
    };

    // The change of the total, the zero line always in view.
    let (y0, y1) =
        span(scenes.iter().flat_map(|s| s.change.iter().map(|p| p.1)).chain([0.0]), false);
    let mut chart = ChartBuilder::on(&top)
        .caption("total energy less its start", ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..t1, y0..y1)
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("E(t) - E(0), J")
        .x_label_formatter(&|x| short(*x))
        .y_label_formatter(&|y| short(*y))
        .draw()
        .map_err(|e| err(path, e))?;
    chart
        .draw_series(LineSeries::new([(0.0, 0.0), (t1, 0.0)], BLACK.mix(0.6)))
        .map_err(|e| err(path, e))?;
    for (k, s) in scenes.iter().enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(finite(&s.change), c.stroke_width(2)))
            .map_err(|e| err(path, e))?
            .label(s.label.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(path, e))?;

    // The kinetic energies, drawn as log10 on a linear axis labelled in J: plotters' log
    // axis leaves out its key points (grid lines and labels) below f64::EPSILON, and a rest
    // state's kinetic energy is round-off, 1e-21 to 1e-15 J.
    let positive = |pts: &[(f64, f64)]| -> Vec<(f64, f64)> {
        pts.iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite() && p.1 > 0.0)
            .map(|p| (p.0, p.1.log10()))
            .collect()
    };
    let logs: Vec<f64> = scenes
        .iter()
        .flat_map(|s| positive(&s.liquid_kinetic).into_iter().chain(positive(&s.body_kinetic)))
        .map(|p| p.1)
        .collect();
    let (k0, k1) = span(logs.into_iter(), false);
    let mut chart = ChartBuilder::on(&bottom)
        .caption("kinetic energy: liquid (solid), bodies (dashed)", ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..t1, k0..k1)
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("kinetic energy, J")
        .y_labels(12)
        .x_label_formatter(&|x| short(*x))
        .y_label_formatter(&|y| short(10f64.powf(*y)))
        .draw()
        .map_err(|e| err(path, e))?;
    for (k, s) in scenes.iter().enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(positive(&s.liquid_kinetic), c.stroke_width(2)))
            .map_err(|e| err(path, e))?;
        let body = positive(&s.body_kinetic);
        if !body.is_empty() {
            chart
                .draw_series(DashedLineSeries::new(body, 8, 5, c.stroke_width(2)))
                .map_err(|e| err(path, e))?;
        }
    }
    root.present().map_err(|e| err(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("diffluid-plot-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d.join(name)
    }

    fn starts_with(path: &Path, magic: &[u8]) -> bool {
        std::fs::read(path).map(|b| b.len() > 100 && b.starts_with(magic)).unwrap_or(false)
    }

    #[test]
    fn writes_pngs_and_a_gif() {
        let p = tmp("loss.png");
        loss_plot(&p, &[1.0, 0.3, 0.05, 0.01], &[2.0, 1.0, 0.4, 0.1]).unwrap();
        assert!(starts_with(&p, b"\x89PNG"));
        assert!(loss_plot(&tmp("empty.png"), &[], &[]).is_err());
        let d = Vec3::new(1.0, 0.8, 1.0);
        let tr = Track {
            label: "path".into(),
            points: vec![Vec3::new(0.2, 0.6, 0.3), Vec3::new(0.5, 0.3, 0.4)],
        };
        // A pool and a box body, as closed meshes.
        let cuboid = |lo: Vec3, hi: Vec3| {
            let (vertices, triangles) =
                parry3d_f64::shape::Cuboid::new(nalgebra::Vector3::from((hi - lo) / 2.0).into())
                    .to_trimesh();
            let c = (lo + hi) / 2.0;
            TriangleMesh { vertices: vertices.into_iter().map(|v| v + c).collect(), triangles }
        };
        let pool = cuboid(Vec3::ZERO, Vec3::new(1.0, 0.3, 1.0));
        let p = tmp("traj.png");
        let body = [cuboid(Vec3::new(0.4, 0.2, 0.4), Vec3::new(0.6, 0.4, 0.6))];
        let picture = Picture { domain: d, liquid: &pool, bodies: &body };
        trajectory_plot(&p, d, &[tr], Some(Vec3::new(0.6, 0.2, 0.5)), Some(("liquid", &picture)))
            .unwrap();
        assert!(starts_with(&p, b"\x89PNG"));
        let p = tmp("anim.gif");
        let frames: Vec<Frame> = (0..3)
            .map(|k| Frame {
                liquid: pool.clone(),
                bodies: vec![cuboid(
                    Vec3::new(0.3, 0.5 - 0.1 * k as f64, 0.4),
                    Vec3::new(0.4, 0.6 - 0.1 * k as f64, 0.5),
                )],
                label: format!("step {k}"),
            })
            .collect();
        animation_gif(&p, d, &frames, View::Side, (320, 240), 100).unwrap();
        assert!(starts_with(&p, b"GIF8"));
        // Every frame decodes, in order, to its drawing: the palette found at GIF_SPEED's
        // sampling keeps the flat colours (at most 1% of pixels off by more than 24 in a
        // channel; the shaded surface's gradients are where it rounds).
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options.read_info(std::fs::File::open(&p).unwrap()).unwrap();
        for (k, f) in frames.iter().enumerate() {
            let got = decoder.read_next_frame().unwrap().expect("a frame").clone();
            assert_eq!((got.width, got.height), (320, 240), "frame {k}");
            let mut rgb = vec![0u8; 3 * 320 * 240];
            {
                let root = BitMapBackend::with_buffer(&mut rgb, (320, 240)).into_drawing_area();
                draw_frame(&root, d, f, View::Side, &p).unwrap();
                root.present().unwrap();
            }
            let off = rgb
                .chunks(3)
                .zip(got.buffer.chunks(4))
                .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > 24))
                .count();
            assert!(off * 100 <= 320 * 240, "frame {k}: {off} pixels off");
        }
        assert!(decoder.read_next_frame().unwrap().is_none(), "more frames than drawn");
        let p = tmp("frame.png");
        frame_png(&p, d, &frames[0], View::Top, (400, 300)).unwrap();
        assert!(starts_with(&p, b"\x89PNG"));
    }

    /// A picture that fails once its file was opened (a PNG frame asked for at a `.gif` path:
    /// the image encoder refuses it) leaves the picture that was there, and no temporary: a
    /// failed `render` replaced a 40 KB GIF with 38 bytes.
    #[test]
    fn a_failed_picture_leaves_the_old_one() {
        let dir = tmp("failed");
        std::fs::create_dir_all(&dir).unwrap();
        let d = Vec3::new(1.0, 0.8, 1.0);
        let frame =
            Frame { liquid: TriangleMesh::default(), bodies: Vec::new(), label: "x".into() };
        let p = dir.join("old.gif");
        std::fs::write(&p, b"the old picture").unwrap();
        assert!(frame_png(&p, d, &frame, View::Side, (120, 90)).is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"the old picture", "the old picture was replaced");
        let left: Vec<_> =
            std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, ["old.gif"], "temporaries left behind");
        std::fs::remove_dir_all(&dir).ok();
    }
}
