//! Rigid bodies: parry shape, mass properties, pose, and the quaternion update (stage `rigid`).
//!
//! A body's state is the world position of its centre of mass `x`, the orientation `q` of
//! its shape frame, its linear velocity `v` and angular velocity `ω` (world frame). The
//! shape's local origin sits at `x − q·c` where `c` is the centre of mass in the shape frame.
//! Mass and inertia come from parry's mass properties; the world inertia is `R·I·Rᵀ`.

use crate::error::{Error, Result};
use crate::geometry::fractions;
use crate::geometry::grid::Grid;
use crate::geometry::interior::{signed_distance, smooth_interior};
use crate::math::dual::Dual;
use crate::math::{twist, Pose, Rotation, SharedShape, Twist, TwistParts, Vec3};
use parry3d_f64::math::Matrix as Mat3;

pub use crate::geometry::spin::Spin;

/// Bodies thinner than this many cells everywhere seal the faces they cross
/// ([`RigidBody::seals`]); static solids from 2 cells down
/// ([`fractions::SEAL_BELOW_CELLS`]).
pub const SEAL_BELOW_CELLS: f64 = 1.0;

/// A rigid body with its state.
#[derive(Clone)]
pub struct RigidBody {
    /// Name from the scene (for outputs).
    pub name: String,
    /// Geometry in the shape frame.
    pub shape: SharedShape,
    /// Centre of mass in the shape frame.
    pub local_com: Vec3,
    /// Mass, kg.
    pub mass: f64,
    /// Inertia tensor about the centre of mass, in the shape frame, kg·m².
    pub local_inertia: Mat3,
    /// Who moves the body.
    pub motion: Motion,
    /// World position of the centre of mass.
    pub x: Vec3,
    /// Orientation of the shape frame (unit quaternion).
    pub q: Rotation,
    /// Linear velocity.
    pub v: Vec3,
    /// Angular velocity, world frame.
    pub w: Vec3,
    /// External force on the centre of mass (world frame, N), applied every step with
    /// gravity until changed.
    pub force: Vec3,
    /// External torque about the centre of mass (world frame, N·m).
    pub torque: Vec3,
    /// Thickness of the shape, 2·V/S (see [`crate::geometry::shape::thickness`]): how finely
    /// its face fractions sample its distance ([`RigidBody::face_fractions`]).
    pub thickness: f64,
    /// Depth of the shape, the radius of its largest inscribed ball (see
    /// [`crate::geometry::shape::depth`]): a body less than half a cell deep (thinner than a cell
    /// everywhere) seals the faces its surface cuts ([`RigidBody::seals`]).
    pub depth: f64,
}

/// Who moves a body.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Motion {
    /// Moved by the liquid, gravity and external forces, and integrated by diffluid.
    #[default]
    Dynamic,
    /// Held still: an obstacle that still couples through J, with zero velocity.
    Fixed,
    /// In the coupled solve like a dynamic body, but moved by the caller (its own rigid-body
    /// engine): diffluid sets its velocity after the solve and leaves its pose alone. See
    /// [`crate::world::Simulation::set_body_state`].
    External,
    /// Moved along its own velocity (a paddle, a wave maker): a prescribed motion the
    /// pressure solve sees as a moving boundary, which no force changes. Its velocity enters
    /// the solve's right-hand side; diffluid integrates its pose.
    Kinematic,
}

/// A body's state: the centre of mass `x`, the orientation `q` of the shape frame, the
/// linear velocity `v` and the angular velocity `ω` (world frame). The one state type of the
/// tape, the gradients, the optimiser and the scene; serialised as
/// `{"v": [..], "w": [..], "x": [..], "q": [w, x, y, z]}`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(from = "StateRepr", into = "StateRepr")]
pub struct BodyState {
    /// Centre of mass.
    pub x: Vec3,
    /// Orientation.
    pub q: Rotation,
    /// Linear velocity.
    pub v: Vec3,
    /// Angular velocity (world).
    pub w: Vec3,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct StateRepr {
    v: [f64; 3],
    w: [f64; 3],
    x: [f64; 3],
    q: [f64; 4],
}

impl From<StateRepr> for BodyState {
    fn from(r: StateRepr) -> Self {
        BodyState {
            x: crate::math::v3(r.x),
            q: Rotation::from_xyzw(r.q[1], r.q[2], r.q[3], r.q[0]).normalize(),
            v: crate::math::v3(r.v),
            w: crate::math::v3(r.w),
        }
    }
}

impl From<BodyState> for StateRepr {
    fn from(s: BodyState) -> Self {
        StateRepr {
            v: s.v.to_array(),
            w: s.w.to_array(),
            x: s.x.to_array(),
            q: [s.q.w, s.q.x, s.q.y, s.q.z],
        }
    }
}

/// One part of a body's initial state, a 3-vector each: the one name for a body parameter
/// in scene files (`"v"`, `"w"`, `"x"`, `"q"`), gradients, the optimiser and the gradient
/// check. The orientation is perturbed in the world-frame tangent space, q → exp(θ)·q.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Param {
    /// Linear velocity.
    V,
    /// Angular velocity.
    W,
    /// Centre of mass.
    X,
    /// Orientation, as a rotation vector in the world frame.
    Q,
}

impl Param {
    /// All four, in order v, ω, x, q.
    pub const ALL: [Param; 4] = [Param::V, Param::W, Param::X, Param::Q];

    /// `"v"`, `"w"`, `"x"` or `"q"`.
    pub fn name(self) -> &'static str {
        match self {
            Param::V => "v",
            Param::W => "w",
            Param::X => "x",
            Param::Q => "q",
        }
    }

    /// The state moved by `h` along axis `axis` of this parameter.
    pub fn perturbed(self, s: &BodyState, axis: usize, h: f64) -> BodyState {
        let e = h * crate::math::unit(axis);
        let mut s = *s;
        match self {
            Param::V => s.v += e,
            Param::W => s.w += e,
            Param::X => s.x += e,
            Param::Q => s.q = (Rotation::from_scaled_axis(e) * s.q).normalize(),
        }
        s
    }
}

impl Motion {
    /// Whether diffluid integrates a body that moves this way (dynamic and kinematic ones).
    pub fn integrated_here(self) -> bool {
        matches!(self, Motion::Dynamic | Motion::Kinematic)
    }
}

impl std::str::FromStr for Param {
    type Err = String;
    fn from_str(s: &str) -> Result<Param, String> {
        Param::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("unknown parameter {s:?}: use \"v\", \"w\", \"x\" or \"q\""))
    }
}

impl TryFrom<String> for Param {
    type Error = String;
    fn try_from(s: String) -> Result<Param, String> {
        s.parse()
    }
}

impl From<Param> for String {
    fn from(p: Param) -> String {
        p.name().into()
    }
}

impl std::fmt::Display for Param {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::fmt::Debug for RigidBody {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RigidBody")
            .field("name", &self.name)
            .field("mass", &self.mass)
            .field("x", &self.x)
            .field("q", &self.q)
            .field("v", &self.v)
            .field("w", &self.w)
            .finish_non_exhaustive()
    }
}

/// How a [`BodyBuilder`] gives a body its mass.
#[derive(Clone, Debug)]
enum MassSpec {
    Density(f64),
    Mass(f64),
    Properties(parry3d_f64::mass_properties::MassProperties),
}

/// Builds a [`RigidBody`] with named settings: its density or mass, pose, motion and
/// velocity ([`RigidBody::builder`]). Unset, a body is dynamic, at rest at the origin's pose,
/// with the density of water (1000 kg/m³: neutrally buoyant in the default fluid).
///
/// ```
/// use diffluid::prelude::*;
///
/// let ball = RigidBody::builder("ball", SharedShape::ball(0.05))
///     .density(500.0)
///     .pose(Pose::from_translation(Vec3::new(0.3, 0.2, 0.2)))
///     .build()?;
/// assert!((ball.mass - 500.0 * 4.0 / 3.0 * std::f64::consts::PI * 0.05f64.powi(3)).abs() < 1e-9);
/// assert!(RigidBody::builder("ghost", SharedShape::ball(0.05)).density(-1.0).build().is_err());
/// # Ok::<(), diffluid::Error>(())
/// ```
#[derive(Clone, Debug)]
#[must_use = "a builder does nothing until .build()"]
pub struct BodyBuilder {
    name: String,
    shape: SharedShape,
    mass: MassSpec,
    pose: Pose,
    motion: Motion,
    v: Vec3,
    w: Vec3,
}

impl BodyBuilder {
    /// Mass properties from a uniform density, kg/m³ (the default: 1000).
    pub fn density(mut self, density: f64) -> Self {
        self.mass = MassSpec::Density(density);
        self
    }

    /// A total mass, kg, spread uniformly over the shape (its inertia that of the shape at
    /// the density that gives this mass).
    pub fn mass(mut self, mass: f64) -> Self {
        self.mass = MassSpec::Mass(mass);
        self
    }

    /// Mass properties in the shape frame, such as a rapier body's
    /// `mass_properties().local_mprops`.
    pub fn mass_properties(mut self, mp: parry3d_f64::mass_properties::MassProperties) -> Self {
        self.mass = MassSpec::Properties(mp);
        self
    }

    /// Where the shape's frame is (default: the identity pose).
    pub fn pose(mut self, pose: Pose) -> Self {
        self.pose = pose;
        self
    }

    /// Who moves the body (default [`Motion::Dynamic`]).
    pub fn motion(mut self, motion: Motion) -> Self {
        self.motion = motion;
        self
    }

    /// Initial linear and angular velocity, world frame (default at rest).
    pub fn velocity(mut self, v: Vec3, w: Vec3) -> Self {
        self.v = v;
        self.w = w;
        self
    }

    /// The body. Errors ([`Error::InvalidSettings`] naming the body): a density or
    /// mass that is not a positive finite number, or a shape whose mass properties are not
    /// finite and positive (an empty or enormous shape). Where the body may go is checked
    /// when a simulation takes it ([`crate::world::Simulation::add_body`]).
    pub fn build(self) -> Result<RigidBody> {
        let invalid = |message: String| Error::InvalidSettings {
            key: format!("body {:?}", self.name),
            message,
        };
        let positive = |what: &str, x: f64| {
            if x.is_finite() && x > 0.0 {
                Ok(x)
            } else {
                Err(invalid(format!("{what} must be a positive number, got {x}")))
            }
        };
        let mp = match &self.mass {
            MassSpec::Density(d) => self.shape.mass_properties(positive("density", *d)?),
            MassSpec::Mass(m) => {
                let m = positive("mass", *m)?;
                let unit = self.shape.mass_properties(1.0);
                self.shape.mass_properties(m / positive("the shape's volume", unit.mass())?)
            }
            MassSpec::Properties(mp) => *mp,
        };
        positive("mass", mp.mass())?;
        if !(mp.principal_inertia().is_finite() && mp.local_com.is_finite()) {
            return Err(invalid("the shape's inertia is not finite (is it too large?)".into()));
        }
        let body =
            RigidBody::with_mass_properties(self.name.clone(), self.shape.clone(), self.pose, &mp);
        Ok(body.with_motion(self.motion).with_velocity(self.v, self.w))
    }
}

impl RigidBody {
    /// A [`BodyBuilder`] for a body named `name` of `shape`, which names its density or
    /// mass, pose, motion and velocity.
    pub fn builder(name: impl Into<String>, shape: SharedShape) -> BodyBuilder {
        BodyBuilder {
            name: name.into(),
            shape,
            mass: MassSpec::Density(1000.0),
            pose: Pose::IDENTITY,
            motion: Motion::Dynamic,
            v: Vec3::ZERO,
            w: Vec3::ZERO,
        }
    }

    /// A body from a shape at a pose, with mass properties at `density` (kg/m³), unchecked
    /// ([`RigidBody::builder`] checks the density).
    pub fn with_density(name: String, shape: SharedShape, pose: Pose, density: f64) -> RigidBody {
        let mp = shape.mass_properties(density);
        RigidBody::with_mass_properties(name, shape, pose, &mp)
    }

    /// A body from a shape at a pose with the given mass properties (in the shape frame),
    /// such as a rapier body's `mass_properties().local_mprops`.
    pub fn with_mass_properties(
        name: String,
        shape: SharedShape,
        pose: Pose,
        mp: &parry3d_f64::mass_properties::MassProperties,
    ) -> RigidBody {
        let r = Mat3::from_quat(mp.principal_inertia_local_frame);
        let local_inertia = r * Mat3::from_diagonal(mp.principal_inertia()) * r.transpose();
        let thickness = crate::geometry::shape::thickness(&shape);
        let depth = crate::geometry::shape::depth(&shape);
        RigidBody {
            name,
            x: pose.transform_point(mp.local_com),
            q: pose.rotation,
            local_com: mp.local_com,
            mass: mp.mass(),
            local_inertia,
            shape,
            motion: Motion::Dynamic,
            v: Vec3::ZERO,
            w: Vec3::ZERO,
            force: Vec3::ZERO,
            torque: Vec3::ZERO,
            thickness,
            depth,
        }
    }

    /// The same body with another [`Motion`].
    pub fn with_motion(mut self, motion: Motion) -> RigidBody {
        self.motion = motion;
        self
    }

    /// The same body with initial linear and angular velocities (world frame).
    pub fn with_velocity(mut self, v: Vec3, w: Vec3) -> RigidBody {
        self.v = v;
        self.w = w;
        self
    }

    /// Whether the body moves under the liquid's forces: it is one of the coupled solve's
    /// bodies (dynamic or external).
    pub fn moves(&self) -> bool {
        matches!(self.motion, Motion::Dynamic | Motion::External)
    }

    /// The state.
    pub fn state(&self) -> BodyState {
        BodyState { x: self.x, q: self.q, v: self.v, w: self.w }
    }

    /// Sets the state.
    pub fn set_state(&mut self, s: &BodyState) {
        self.x = s.x;
        self.q = s.q;
        self.v = s.v;
        self.w = s.w;
    }

    /// Scales mass and inertia so the body weighs `mass` kg.
    pub fn set_mass(&mut self, mass: f64) {
        let s = mass / self.mass;
        self.mass = mass;
        self.local_inertia *= s;
    }

    /// Volume of the shape, m³.
    pub fn volume(&self) -> f64 {
        self.shape.mass_properties(1.0).mass()
    }

    /// Pose of the shape frame.
    pub fn pose(&self) -> Pose {
        Pose::from_parts(self.x - self.q * self.local_com, self.q)
    }

    /// Signed distance at a world point (negative inside): parry's, but inside a box, a
    /// convex hull or a cylinder smoothed across the planes that bisect its edges (see
    /// [`crate::geometry::interior`]), where the true distance has a kink that the face
    /// fractions would carry into the forward map.
    #[inline]
    pub fn sdf(&self, p: Vec3) -> f64 {
        signed_distance(&self.shape, &self.pose(), p)
    }

    /// Signed distance at `p` with its derivative along the six pose directions
    /// [δx (3); δθ (3)], the body translated by δx and turned by δθ (world frame) about its
    /// centre of mass: ∂φ/∂x = −n, ∂φ/∂θ = −(p − x) × n, with n the gradient of the
    /// distance (the unit vector from the closest surface point, or the smoothed interior
    /// distance's gradient where [`RigidBody::sdf`] smooths it).
    pub fn sdf_pose_dual(&self, p: Vec3) -> Dual<6> {
        let pose = self.pose();
        if let Some((phi, g)) = smooth_interior(&self.shape, pose.inverse_transform_point(p)) {
            let n = self.q * g;
            let t = (p - self.x).cross(n);
            return Dual::new(phi, [-n.x, -n.y, -n.z, -t.x, -t.y, -t.z]);
        }
        let proj = self.shape.project_point(&pose, p, false);
        let diff = p - proj.point;
        let len = diff.length();
        let phi = if proj.is_inside { -len } else { len };
        let n = if len > 1e-9 {
            if proj.is_inside {
                -diff / len
            } else {
                diff / len
            }
        } else {
            // On the surface (a sample on a flat face of an axis-aligned box is common): the
            // distance still moves as −n·δx, with n from a central difference across it.
            let h = 1e-7 * (1.0 + p.length());
            let g = Vec3::new(
                self.sdf(p + Vec3::X * h) - self.sdf(p - Vec3::X * h),
                self.sdf(p + Vec3::Y * h) - self.sdf(p - Vec3::Y * h),
                self.sdf(p + Vec3::Z * h) - self.sdf(p - Vec3::Z * h),
            );
            g.normalize_or_zero()
        };
        let t = (p - self.x).cross(n);
        Dual::new(phi, [-n.x, -n.y, -n.z, -t.x, -t.y, -t.z])
    }

    /// Sub-boxes per cell side of the body's face fractions on cells of side `dx`
    /// ([`fractions::samples_per_cell`] of its thickness).
    pub fn samples_per_cell(&self, dx: f64) -> usize {
        fractions::samples_per_cell(self.thickness, dx)
    }

    /// Whether the body seals the faces its surface cuts between two cell centres on cells of
    /// side `dx`: it is less than half a cell deep, thinner than [`SEAL_BELOW_CELLS`] (one
    /// cell) everywhere. A body a cell thick or more moves the liquid by its fractions alone
    /// (a disk a cell thick falls within 5% of potential flow unsealed; the liquid sealed
    /// faces carry weighs on it, 23% slow); a thinner one lets the liquid through (half a
    /// cell: twice too fast). See `docs/method.md`, "Moving thin bodies".
    pub fn seals(&self, dx: f64) -> bool {
        self.depth < 0.5 * SEAL_BELOW_CELLS * dx
    }

    /// The body's face fractions where it is now, volume-consistent (see
    /// [`fractions::body_faces`]), sampled as finely as its thickness needs.
    pub fn face_fractions(&self, grid: &Grid) -> fractions::BodyFaces {
        let r = self.samples_per_cell(grid.dx);
        fractions::body_faces(grid, self.bounds(), |p| self.sdf(p), Some(self.volume()), r)
    }

    /// [`RigidBody::face_fractions`] with their derivatives along the six pose directions
    /// (those of [`RigidBody::sdf_pose_dual`]).
    pub fn face_fractions_dual(&self, grid: &Grid) -> [Vec<(usize, Dual<6>)>; 3] {
        let r = self.samples_per_cell(grid.dx);
        let sdf = |p| self.sdf_pose_dual(p);
        fractions::body_faces_generic(grid, self.bounds(), sdf, Some(self.volume()), r)
    }

    /// World inertia tensor R·I·Rᵀ about the centre of mass.
    pub fn world_inertia(&self) -> Mat3 {
        world_inertia(&self.local_inertia, self.q)
    }

    /// Rigid velocity at a world point.
    #[inline]
    pub fn velocity_at(&self, p: Vec3) -> Vec3 {
        self.v + self.w.cross(p - self.x)
    }

    /// The external force and torque, [f; τ] (world frame, N and N·m).
    pub fn load(&self) -> Twist {
        twist(self.force, self.torque)
    }

    /// Sets the external force and torque from [f; τ].
    pub fn set_load(&mut self, load: &Twist) {
        (self.force, self.torque) = (load.linear(), load.angular());
    }

    /// Which part of the body's rotation reaches the liquid ([`Spin`]). Pressure acts along
    /// the surface normal. Every normal of a ball passes through its centre, and every normal
    /// of a capsule, cylinder or cone meets its axis, so the liquid exerts no torque on a
    /// ball about its centre nor on those about their axis, and that spin pushes no liquid.
    /// The face fractions hold such a body's volume but not the symmetry of its surface (at
    /// a given depth their centroid is off the axis by about 1e-4 of a cell), so the discrete
    /// pressure torque J·p along a symmetry axis is not zero; nothing resists that spin, so
    /// it grew without end (a ball floating at rest spun up and stirred the water, issue
    /// 33). The coupling therefore leaves it out: J's torque rows are projected off the
    /// symmetry axes, and the faces the body covers carry the rest of its rigid velocity.
    /// A body whose centre of mass is off the axis keeps its whole rotation.
    pub fn spin(&self) -> Spin {
        let radius = self.shape.compute_local_bounding_sphere().radius;
        let on_axis = |point: Vec3, axis: Vec3| {
            (self.local_com - point).cross(axis).length() <= 1e-12 * radius
        };
        if self.shape.as_ball().is_some() && self.local_com.length() <= 1e-12 * radius {
            return Spin::None;
        }
        let local = if let Some(c) = self.shape.as_capsule() {
            let axis = (c.segment.b - c.segment.a).normalize_or_zero();
            (axis != Vec3::ZERO && on_axis(c.segment.a, axis)).then_some(axis)
        } else if self.shape.as_cylinder().is_some() || self.shape.as_cone().is_some() {
            on_axis(Vec3::ZERO, Vec3::Y).then_some(Vec3::Y)
        } else {
            None
        };
        match local {
            Some(l) => Spin::AcrossAxis(self.q * l),
            None => Spin::Whole,
        }
    }

    /// The velocity the liquid sees on the body's surface at a world point: the rigid
    /// velocity with the spin [`RigidBody::spin`] leaves out removed.
    #[inline]
    pub fn liquid_velocity_at(&self, p: Vec3) -> Vec3 {
        self.v + self.spin().project(self.w).cross(p - self.x)
    }

    /// World bounds of the shape.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let aabb = self.shape.compute_aabb(&self.pose());
        (aabb.mins, aabb.maxs)
    }

    /// The `rigid` stage for one body: x += Δt·v; q += Δt/2·[0, ω]⊗q, then normalised (the paper's f_x); for a
    /// dynamic body, then ω ← I_w(q')⁻¹·I_w(q)·ω ([`carry_angular_momentum`]), which keeps
    /// its world angular momentum (the gyroscopic term ω × Iω, integrated exactly). A
    /// kinematic body keeps its prescribed ω.
    pub fn integrate(&mut self, dt: f64) {
        if !self.motion.integrated_here() {
            return;
        }
        self.x += dt * self.v;
        let q0 = self.q;
        self.q = quat_step(q0, self.w, dt);
        if self.motion == Motion::Dynamic {
            self.w = carry_angular_momentum(&self.local_inertia, q0, self.q, self.w);
        }
    }

    /// The world inertia at orientation `q`.
    pub fn world_inertia_at(&self, q: Rotation) -> Mat3 {
        world_inertia(&self.local_inertia, q)
    }
}

/// R(q)·I·R(q)ᵀ.
#[inline]
fn world_inertia(local: &Mat3, q: Rotation) -> Mat3 {
    let r = Mat3::from_quat(q);
    r * *local * r.transpose()
}

/// The angular velocity at `q1` with the world angular momentum I_w(q0)·ω it had at `q0`:
/// I_w(q1)⁻¹·I_w(q0)·ω. Free of torque, a rigid body's angular momentum is constant while
/// its world inertia turns with it (Euler's equations, the gyroscopic term ω × Iω), so a
/// step that keeps ω would change it; this keeps it exactly.
pub fn carry_angular_momentum(local: &Mat3, q0: Rotation, q1: Rotation, w: Vec3) -> Vec3 {
    world_inertia(local, q1).inverse() * (world_inertia(local, q0) * w)
}

/// Adjoint of [`carry_angular_momentum`]: from ∂L/∂ω₁, (∂L/∂θ₀, ∂L/∂θ₁, ∂L/∂ω) with θ the
/// world-frame tangents of q0 and q1 (q → exp(θ)·q). With L = I₀ω, y = I₁⁻¹ω̄₁ and ω₁ = I₁⁻¹L,
/// and δI = \[δθ\]×I − I\[δθ\]×: ω̄ = I₀·y, θ̄₀ = L × y − ω × I₀y, θ̄₁ = ω₁ × ω̄₁ − L × y.
pub fn carry_angular_momentum_adjoint(
    local: &Mat3,
    q0: Rotation,
    q1: Rotation,
    w: Vec3,
    w1_bar: Vec3,
) -> (Vec3, Vec3, Vec3) {
    let (i0, i1inv) = (world_inertia(local, q0), world_inertia(local, q1).inverse());
    let l = i0 * w;
    let w1 = i1inv * l;
    let y = i1inv * w1_bar;
    let iy = i0 * y;
    (l.cross(y) - w.cross(iy), w1.cross(w1_bar) - l.cross(y), iy)
}

/// `q + Δt/2·[0, ω]⊗q`, before normalisation.
#[inline]
fn quat_step_raw(q: Rotation, w: Vec3, dt: f64) -> Rotation {
    let wq = Rotation::from_xyzw(w.x, w.y, w.z, 0.0) * q;
    Rotation::from_xyzw(
        q.x + 0.5 * dt * wq.x,
        q.y + 0.5 * dt * wq.y,
        q.z + 0.5 * dt * wq.z,
        q.w + 0.5 * dt * wq.w,
    )
}

/// `normalise(q + Δt/2·[0, ω]⊗q)`.
#[inline]
pub fn quat_step(q: Rotation, w: Vec3, dt: f64) -> Rotation {
    quat_step_raw(q, w, dt).normalize()
}

/// Adjoint of [`quat_step`]: given ∂L/∂q' (as a 4-vector in a quaternion), returns
/// (∂L/∂q, ∂L/∂ω). With r = q + Δt/2·[0, ω]⊗q and q' = r/|r|:
/// r̄ = (q̄' − q'·(q'·q̄'))/|r|, q̄ = r̄ + Δt/2·L([0, ω])ᵀ r̄ = r̄ − Δt/2·[0, ω]⊗r̄, and
/// ω̄ = Δt/2·vec(r̄ ⊗ q*), using L(p)ᵀ = L(p*) and R(q)ᵀ = R(q*) for the left and right
/// multiplication matrices.
pub fn quat_step_adjoint(q: Rotation, w: Vec3, dt: f64, qbar_out: Rotation) -> (Rotation, Vec3) {
    let r = quat_step_raw(q, w, dt);
    let len = r.length();
    let qn = r * (1.0 / len);
    let proj = qn.dot(qbar_out);
    let rbar = (qbar_out - qn * proj) * (1.0 / len);
    let wr = Rotation::from_xyzw(w.x, w.y, w.z, 0.0) * rbar;
    let qbar = rbar - wr * (0.5 * dt);
    let t = rbar * q.conjugate();
    (qbar, Vec3::new(t.x, t.y, t.z) * (0.5 * dt))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_derivative_of_the_distance_matches_central_differences() {
        let mut b = RigidBody::with_density(
            "c".into(),
            SharedShape::cuboid(0.2, 0.1, 0.15),
            Pose::from_parts(
                Vec3::new(0.5, 0.4, 0.3),
                Rotation::from_axis_angle(Vec3::new(1.0, 2.0, 0.5).normalize(), 0.6),
            ),
            1000.0,
        );
        let eps = 1e-7;
        for p in
            [Vec3::new(0.55, 0.47, 0.31), Vec3::new(0.9, 0.2, 0.3), Vec3::new(0.45, 0.38, 0.33)]
        {
            let d = b.sdf_pose_dual(p);
            assert!((d.v - b.sdf(p)).abs() < 1e-14);
            for k in 0..6 {
                let e = crate::math::unit(k % 3) * eps;
                let (x0, q0) = (b.x, b.q);
                let mut f = |sgn: f64| {
                    if k < 3 {
                        b.x = x0 + sgn * e;
                    } else {
                        b.q = (Rotation::from_scaled_axis(sgn * e) * q0).normalize();
                    }
                    let v = b.sdf(p);
                    b.x = x0;
                    b.q = q0;
                    v
                };
                let fd = (f(1.0) - f(-1.0)) / (2.0 * eps);
                assert!((fd - d.d[k]).abs() < 1e-6, "point {p}, direction {k}: {fd} vs {}", d.d[k]);
            }
        }
    }

    #[test]
    fn cube_mass_properties() {
        let b = RigidBody::with_density(
            "c".into(),
            SharedShape::cuboid(0.1, 0.1, 0.1),
            Pose::IDENTITY,
            2000.0,
        );
        assert!((b.mass - 16.0).abs() < 1e-12);
        // I = m (a² + a²)/12 with a = 0.2.
        let i = 16.0 * (0.04 + 0.04) / 12.0;
        assert!((b.world_inertia().x_axis.x - i).abs() < 1e-12);
    }

    #[test]
    fn quaternion_step_adjoint_matches_central_differences() {
        let q = Rotation::from_axis_angle(Vec3::new(0.3, -0.5, 0.8).normalize(), 0.7);
        let w = Vec3::new(1.1, -0.4, 2.3);
        let dt = 0.05;
        let qbar_out = Rotation::from_xyzw(0.3, -1.2, 0.5, 0.8);
        let (qbar, wbar) = quat_step_adjoint(q, w, dt, qbar_out);
        let f = |q: Rotation, w: Vec3| quat_step(q, w, dt).dot(qbar_out);
        let eps = 1e-6;
        for d in 0..3 {
            let e = crate::math::unit(d) * eps;
            let fd = (f(q, w + e) - f(q, w - e)) / (2.0 * eps);
            assert!((fd - crate::math::comp(wbar, d)).abs() < 1e-9, "ω[{d}]: {fd} vs {wbar}");
        }
        for d in 0..4 {
            let mut a = [0.0; 4];
            a[d] = eps;
            let e = Rotation::from_xyzw(a[0], a[1], a[2], a[3]);
            let fd = (f(q + e, w) - f(q - e, w)) / (2.0 * eps);
            let an = qbar.to_array()[d];
            assert!((fd - an).abs() < 1e-9, "q[{d}]: {fd} vs {an}");
        }
    }

    /// ∂L/∂(q0, q1, ω) of the angular-momentum carry against central differences.
    #[test]
    fn angular_momentum_carry_adjoint_matches_central_differences() {
        let b = RigidBody::with_density(
            "b".into(),
            SharedShape::cuboid(0.3, 0.1, 0.2),
            Pose::IDENTITY,
            700.0,
        );
        let li = b.local_inertia;
        let q0 = Rotation::from_axis_angle(Vec3::new(0.3, -0.5, 0.8).normalize(), 0.7);
        let q1 = Rotation::from_axis_angle(Vec3::new(0.2, 0.5, -0.4).normalize(), 1.1);
        let w = Vec3::new(1.1, -0.4, 2.3);
        let bar = Vec3::new(0.3, -1.2, 0.5);
        let (g0, g1, gw) = carry_angular_momentum_adjoint(&li, q0, q1, w, bar);
        let f =
            |q0: Rotation, q1: Rotation, w: Vec3| carry_angular_momentum(&li, q0, q1, w).dot(bar);
        let eps = 1e-6;
        let turn = |q: Rotation, k: usize, s: f64| {
            (Rotation::from_scaled_axis(s * eps * crate::math::unit(k)) * q).normalize()
        };
        for k in 0..3 {
            let e = eps * crate::math::unit(k);
            let checks = [
                ((f(turn(q0, k, 1.0), q1, w) - f(turn(q0, k, -1.0), q1, w)) / (2.0 * eps), g0),
                ((f(q0, turn(q1, k, 1.0), w) - f(q0, turn(q1, k, -1.0), w)) / (2.0 * eps), g1),
                ((f(q0, q1, w + e) - f(q0, q1, w - e)) / (2.0 * eps), gw),
            ];
            for (fd, g) in checks {
                let ad = crate::math::comp(g, k);
                assert!((fd - ad).abs() < 1e-7 * fd.abs().max(1.0), "axis {k}: {fd} vs {ad}");
            }
        }
    }

    /// An asymmetric box spinning in free flight keeps its world angular momentum: over 1,000
    /// steps of 0.01 s with ω = (1.1, −0.4, 2.3) it drifts by 2e-15 relative (a step that
    /// kept ω instead turned it by 14%).
    #[test]
    fn free_flight_keeps_the_world_angular_momentum() {
        let mut b = RigidBody::with_density(
            "b".into(),
            SharedShape::cuboid(0.3, 0.1, 0.2),
            Pose::IDENTITY,
            700.0,
        );
        b.w = Vec3::new(1.1, -0.4, 2.3);
        let l0 = b.world_inertia() * b.w;
        for _ in 0..1000 {
            b.integrate(0.01);
        }
        let l = b.world_inertia() * b.w;
        let err = (l - l0).length() / l0.length();
        assert!(err < 1e-6, "angular momentum drifted by {err:e}");
    }

    #[test]
    fn quaternion_step_turns_at_omega() {
        // Many small steps about z at 1 rad/s for 1 s turn by about 1 rad.
        let mut q = Rotation::IDENTITY;
        for _ in 0..1000 {
            q = quat_step(q, Vec3::new(0.0, 0.0, 1.0), 1e-3);
        }
        let (axis, angle) = q.to_axis_angle();
        assert!((angle - 1.0).abs() < 1e-6 && (axis.z - 1.0).abs() < 1e-9, "{axis} {angle}");
    }
}
