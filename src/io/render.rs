//! Pictures of the liquid and the bodies without a GPU: an orthographic software rasteriser
//! of triangle meshes with a depth buffer, smooth (vertex-normal) Lambert shading, and the
//! liquid drawn translucent over the bodies behind it, so a body under water stays visible.
//! The charts (`plot`) place these images under their axes.

use crate::math::Vec3;

pub use crate::geometry::mesh::TriangleMesh;

/// Which way the camera looks at the tank.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum View {
    /// From the front (+z) towards −z: x to the right, y up.
    Side,
    /// From above (+y) down: x to the right, z up the picture (the x–z chart's axes; the
    /// picture is the view from above mirrored top to bottom).
    Top,
}

impl View {
    /// The picture's (width, height) in metres for a tank of extent `domain`.
    pub fn extent(self, domain: Vec3) -> (f64, f64) {
        let (w, h, _) = self.project(domain);
        (w, h)
    }

    /// (right, up, towards the camera) components of a world point.
    fn project(self, p: Vec3) -> (f64, f64, f64) {
        match self {
            View::Side => (p.x, p.y, p.z),
            View::Top => (p.x, p.z, p.y),
        }
    }
}

/// An RGB picture, rows from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Red, green, blue per pixel, row by row.
    pub rgb: Vec<u8>,
}

/// What a picture shows: the liquid's surface and the bodies' surfaces, in the box from the
/// origin to `domain`.
#[derive(Clone, Copy, Debug)]
pub struct Picture<'a> {
    /// The tank's extent, m.
    pub domain: Vec3,
    /// The liquid surface.
    pub liquid: &'a TriangleMesh,
    /// The bodies' surfaces.
    pub bodies: &'a [TriangleMesh],
}

const WATER: [f64; 3] = [45.0, 120.0, 215.0];
const BODY: [f64; 3] = [235.0, 150.0, 60.0];
const BACKGROUND: [f64; 3] = [255.0, 255.0, 255.0];
/// How much of a pixel the liquid covers over the background.
const WATER_OPACITY: f64 = 0.55;
/// What the water lets through of a body behind it, per channel.
const UNDER_WATER: [f64; 3] = [0.85, 0.92, 1.0];

/// One shaded layer: depth (towards the camera is larger) and colour per pixel.
struct Layer {
    depth: Vec<f64>,
    colour: Vec<[f64; 3]>,
}

impl Layer {
    fn new(len: usize) -> Layer {
        Layer { depth: vec![f64::NEG_INFINITY; len], colour: vec![[0.0; 3]; len] }
    }
}

/// Renders `picture` seen from `view` at `width` × `height` pixels, the domain's extent in
/// the view filling the picture.
pub fn render(picture: &Picture, view: View, width: u32, height: u32) -> Image {
    let len = (width * height) as usize;
    let mut liquid = Layer::new(len);
    let mut bodies = Layer::new(len);
    let (w, h) = view.extent(picture.domain);
    let frame = Frame { view, sx: width as f64 / w, sy: height as f64 / h, width, height };
    frame.rasterise(picture.liquid, WATER, &mut liquid);
    for b in picture.bodies {
        frame.rasterise(b, BODY, &mut bodies);
    }
    let mut rgb = Vec::with_capacity(3 * len);
    for i in 0..len {
        let body = bodies.depth[i] > f64::NEG_INFINITY;
        let c = match (liquid.depth[i] > bodies.depth[i], body) {
            // A body seen through the water: its own colour, filtered blue, so it stays
            // recognisable.
            (true, true) => [0, 1, 2].map(|k| {
                let filtered = bodies.colour[i][k] * UNDER_WATER[k];
                0.25 * liquid.colour[i][k] + 0.75 * filtered
            }),
            (true, false) => [0, 1, 2].map(|k| {
                WATER_OPACITY * liquid.colour[i][k] + (1.0 - WATER_OPACITY) * BACKGROUND[k]
            }),
            (false, true) => bodies.colour[i],
            (false, false) => BACKGROUND,
        };
        rgb.extend(c.map(|x| x.round().clamp(0.0, 255.0) as u8));
    }
    Image { width, height, rgb }
}

/// The projection onto pixels.
struct Frame {
    view: View,
    sx: f64,
    sy: f64,
    width: u32,
    height: u32,
}

impl Frame {
    /// Draws `mesh` into `layer`, nearest surface winning, lit from the upper left in front,
    /// shaded by interpolated vertex normals where the surface is smooth; a corner whose
    /// vertex normal is more than 30° from its triangle's takes the triangle's (a box's flat
    /// faces and sharp edges stay flat and sharp, a ball stays round).
    fn rasterise(&self, mesh: &TriangleMesh, base: [f64; 3], layer: &mut Layer) {
        let light = Vec3::new(-0.45, 0.75, 0.5).normalize();
        let mut normals = vec![Vec3::ZERO; mesh.vertices.len()];
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            // Area-weighted: the cross product's length is twice the area.
            let n = (b - a).cross(c - a);
            for &i in t {
                normals[i as usize] += n;
            }
        }
        let screen: Vec<(f64, f64, f64)> = mesh
            .vertices
            .iter()
            .map(|&p| {
                let (u, v, d) = self.view.project(p);
                (u * self.sx, (self.height as f64) - v * self.sy, d)
            })
            .collect();
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| screen[i as usize]);
            let area = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
            if area.abs() < 1e-12 {
                continue;
            }
            let x0 = a.0.min(b.0).min(c.0).floor().max(0.0) as u32;
            let x1 = (a.0.max(b.0).max(c.0).ceil() as i64).clamp(0, self.width as i64) as u32;
            let y0 = a.1.min(b.1).min(c.1).floor().max(0.0) as u32;
            let y1 = (a.1.max(b.1).max(c.1).ceil() as i64).clamp(0, self.height as i64) as u32;
            let face = {
                let [p, q, r] = t.map(|i| mesh.vertices[i as usize]);
                (q - p).cross(r - p).normalize_or_zero()
            };
            let [na, nb, nc] = t.map(|i| {
                let n = normals[i as usize].normalize_or_zero();
                if n.dot(face) > 0.866 {
                    n
                } else {
                    face
                }
            });
            for y in y0..y1 {
                for x in x0..x1 {
                    let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                    // Barycentric weights from the signed sub-areas.
                    let wa = ((b.0 - px) * (c.1 - py) - (b.1 - py) * (c.0 - px)) / area;
                    let wb = ((c.0 - px) * (a.1 - py) - (c.1 - py) * (a.0 - px)) / area;
                    let wc = 1.0 - wa - wb;
                    if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                        continue;
                    }
                    let depth = wa * a.2 + wb * b.2 + wc * c.2;
                    let i = (y * self.width + x) as usize;
                    if depth <= layer.depth[i] {
                        continue;
                    }
                    let n = (wa * na + wb * nb + wc * nc).normalize_or_zero();
                    let lit = 0.4 + 0.6 * n.dot(light).abs();
                    layer.depth[i] = depth;
                    layer.colour[i] = base.map(|c| c * lit);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube(lo: Vec3, hi: Vec3) -> TriangleMesh {
        let v = |i: u32| {
            Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            )
        };
        let quads =
            [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        TriangleMesh {
            vertices: (0..8).map(v).collect(),
            triangles: quads
                .iter()
                .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
                .collect(),
        }
    }

    fn pixel(img: &Image, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y * img.width + x) as usize;
        [img.rgb[i], img.rgb[i + 1], img.rgb[i + 2]]
    }

    /// A pool filling the lower half of the tank covers the lower half of a side view and
    /// all of a top view; a body inside it shows through, tinted; above it, the body is
    /// drawn as it is.
    #[test]
    fn liquid_and_bodies_land_where_they_are() {
        let domain = Vec3::new(2.0, 1.0, 1.0);
        let pool = cube(Vec3::ZERO, Vec3::new(2.0, 0.5, 1.0));
        let under = cube(Vec3::new(0.2, 0.1, 0.4), Vec3::new(0.4, 0.3, 0.6));
        let over = cube(Vec3::new(1.6, 0.7, 0.4), Vec3::new(1.8, 0.9, 0.6));
        let bodies = [under, over];
        let picture = Picture { domain, liquid: &pool, bodies: &bodies };
        let side = render(&picture, View::Side, 200, 100);
        let white = [255, 255, 255];
        assert_eq!(pixel(&side, 100, 10), white, "air above the pool");
        let water = pixel(&side, 100, 90);
        assert!(water[2] > water[0] && water != white, "{water:?}");
        let tinted = pixel(&side, 30, 80);
        let warmth = |c: [u8; 3]| c[0] as i32 - c[2] as i32;
        assert!(warmth(tinted) > warmth(water), "the body under water: {tinted:?} {water:?}");
        let dry = pixel(&side, 170, 20);
        assert!(dry[0] > dry[2] && dry[0] > 150, "the body in air: {dry:?}");
        let top = render(&picture, View::Top, 200, 100);
        for (x, y) in [(5, 5), (100, 50), (195, 95)] {
            let p = pixel(&top, x, y);
            assert!(p[2] > p[0], "top view at {x},{y}: {p:?}");
        }
        // The body above the water is seen from above, untinted, where its x–z square is.
        assert!(pixel(&top, 170, 50)[0] > 150);
    }
}
