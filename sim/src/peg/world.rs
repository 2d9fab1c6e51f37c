//! The rapier world of the peg-in-hole task: a fixed block with a square
//! hole, a dynamic peg held by the robot through a spring-damper coupling,
//! and the contact wrench the wrist sensor reads.
//!
//! Units inside rapier: millimetres, kilograms, seconds, so a force is in
//! kg·mm/s² = mN and a moment in mN·mm. The f64 build of rapier is used:
//! clearances are 25–50 µm at positions of ~30 mm, and f32's 7 digits would
//! leave only ~3 µm of resolution there, too close for contact tolerances.
//! rapier's tolerances scale with `length_unit`; it stays 1, so with lengths
//! in mm the contact slop is 5 µm and the prediction distance 20 µm, well
//! below the clearance (length_unit = 1000, "mm as such", would make the
//! slop 5 mm).
//!
//! Frames: the world frame is the hole frame, origin at the centre of the
//! hole entrance, z up along the hole axis, the hole going down to
//! z = −depth. The peg body's origin is its tip (bottom-face centre), its
//! axis is local +z, and the flange (robot attachment and sensor origin) is
//! the top-face centre at local (0, 0, length).
//!
//! Why a coupling: a kinematic body pushed into a fixed one exchanges no
//! impulse in rapier, so the peg is dynamic and the robot drives it through
//! a stiff spring-damper standing for robot and sensor compliance. The
//! moving mass is the robot's reflected mass, placed at the flange with an
//! isotropic inertia, so the momentum balance below is exact.

use rapier3d_f64::math::{Pose, Rotation, Vector};
use rapier3d_f64::parry::mass_properties::MassProperties;
use rapier3d_f64::parry::query;
use rapier3d_f64::prelude::*;

use super::config::PegConfig;

/// mN per N and mN·mm per N·mm: rapier's force unit is 1e-3 N.
const INTERNAL_PER_NEWTON: f64 = 1e3;

/// Spring-damper gains in rapier's internal units.
#[derive(Debug, Clone, Copy)]
struct CouplingGains {
    k_lin: Vector,
    c_lin: Vector,
    k_rot: f64,
    c_rot: f64,
}

/// What one control step measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Contact force the hole exerts on the peg, hole frame, N; averaged over
    /// the control step (the sensor's low-pass).
    pub force_n: [f64; 3],
    /// Contact moment about the flange (sensor origin), hole frame, N·mm.
    pub moment_nmm: [f64; 3],
}

/// The physics state of one episode.
pub struct PegWorld {
    bodies: RigidBodySet,
    colliders: ColliderSet,
    islands: IslandManager,
    broad_phase: DefaultBroadPhase,
    narrow_phase: NarrowPhase,
    impulse_joints: ImpulseJointSet,
    multibody_joints: MultibodyJointSet,
    soft_bodies: SoftBodySet,
    ccd: CCDSolver,
    params: IntegrationParameters,
    /// Workspace only (rapier keeps no state in it), so a snapshot takes a
    /// fresh one.
    pipeline: PhysicsPipeline,
    peg: RigidBodyHandle,
    peg_collider: ColliderHandle,
    hole_colliders: Vec<ColliderHandle>,
    gains: CouplingGains,
    flange_local: Vector,
    mass: f64,
    inertia: f64,
    substeps: usize,
    control_period: f64,
}

impl Clone for PegWorld {
    fn clone(&self) -> Self {
        PegWorld {
            bodies: self.bodies.clone(),
            colliders: self.colliders.clone(),
            islands: self.islands.clone(),
            broad_phase: self.broad_phase.clone(),
            narrow_phase: self.narrow_phase.clone(),
            impulse_joints: self.impulse_joints.clone(),
            multibody_joints: self.multibody_joints.clone(),
            soft_bodies: self.soft_bodies.clone(),
            ccd: self.ccd.clone(),
            params: self.params,
            pipeline: PhysicsPipeline::new(),
            peg: self.peg,
            peg_collider: self.peg_collider,
            hole_colliders: self.hole_colliders.clone(),
            gains: self.gains,
            flange_local: self.flange_local,
            mass: self.mass,
            inertia: self.inertia,
            substeps: self.substeps,
            control_period: self.control_period,
        }
    }
}

/// The solver settings of a world: the step, the iterations and the
/// contact model tuned for sub-millimetre clearances.
fn integration_parameters(cfg: &PegConfig) -> IntegrationParameters {
    let mut params = IntegrationParameters::default();
    params.dt = cfg.controller.control_period_s / cfg.physics.substeps as f64;
    params.num_solver_iterations = cfg.physics.solver_iterations;
    params.length_unit = 1.0; // see the module comment: mm, slop 5 µm
    // Recycling would keep contacts up to 50 µm stale: the clearance.
    params.contact_recycling = false;
    // Motions per step are far below any shape's size: no CCD needed.
    params.max_ccd_substeps = 0;
    // rapier's contacts are soft constraints whose stiffness is the
    // body mass times (2π·f)²; the default 30–60 Hz would be softer than
    // the coupling and let the peg sink into the floor. 2 kHz is rigid
    // at these masses.
    params.static_contact_softness = SpringCoefficients::new(2000.0, 1.0);
    params.contact_softness = SpringCoefficients::new(2000.0, 1.0);
    // Speculative contacts reach 40 µm: past rapier's 20 µm default, but
    // below both groups' clearances (50 and 25 µm per side) plus a bit,
    // because a margin wider than the gap brakes the peg as it slides past
    // the hole edge ("ghost" contacts; 0.5 mm did). Misses are instead
    // kept small by 8 physics steps per control step (75 µm of travel).
    params.normalized_prediction_distance = 0.04;
    // Push penetration out at up to 50 mm/s rather than 3 mm/s: with the
    // default, penetration under lateral load reached 18 µm; now 2–3 µm.
    params.normalized_max_corrective_velocity = 50.0;
    params
}

impl PegWorld {
    /// Builds the hole block and the peg with its tip at `tip_pose`, at rest.
    pub fn new(cfg: &PegConfig, tip_pose: Pose) -> Self {
        let g = &cfg.geometry;
        let params = integration_parameters(cfg);

        let mut bodies = RigidBodySet::new();
        let mut colliders = ColliderSet::new();
        let block = bodies.insert(RigidBodyBuilder::fixed());
        let hole_colliders = hole_shapes(cfg)
            .into_iter()
            .map(|builder| colliders.insert_with_parent(builder.friction(cfg.contact.friction), block, &mut bodies))
            .collect();

        let c = &cfg.coupling;
        let mass = c.moving_mass_kg;
        let inertia = c.moving_inertia_kg_mm2;
        let flange_local = Vector::new(0.0, 0.0, g.peg_length_mm);
        let peg = bodies.insert(
            RigidBodyBuilder::dynamic()
                .pose(tip_pose)
                .can_sleep(false)
                .additional_mass_properties(MassProperties::new(flange_local, mass, Vector::splat(inertia))),
        );
        let peg_collider = colliders.insert_with_parent(
            peg_shape(cfg).density(0.0).friction(cfg.contact.friction),
            peg,
            &mut bodies,
        );

        let k_lat = c.lateral_stiffness_n_per_mm * INTERNAL_PER_NEWTON;
        let k_ax = c.axial_stiffness_n_per_mm * INTERNAL_PER_NEWTON;
        let k_rot = c.rotational_stiffness_nmm_per_rad * INTERNAL_PER_NEWTON;
        let damping = |k: f64, m: f64| 2.0 * c.damping_ratio * (k * m).sqrt();
        let gains = CouplingGains {
            k_lin: Vector::new(k_lat, k_lat, k_ax),
            c_lin: Vector::new(damping(k_lat, mass), damping(k_lat, mass), damping(k_ax, mass)),
            k_rot,
            c_rot: damping(k_rot, inertia),
        };

        PegWorld {
            bodies,
            colliders,
            islands: IslandManager::new(),
            broad_phase: DefaultBroadPhase::default(),
            narrow_phase: NarrowPhase::new(),
            impulse_joints: ImpulseJointSet::new(),
            multibody_joints: MultibodyJointSet::new(),
            soft_bodies: SoftBodySet::new(),
            ccd: CCDSolver::new(),
            params,
            pipeline: PhysicsPipeline::new(),
            peg,
            peg_collider,
            hole_colliders,
            gains,
            flange_local,
            mass,
            inertia,
            substeps: cfg.physics.substeps,
            control_period: cfg.controller.control_period_s,
        }
    }

    /// The peg's tip pose in the hole frame.
    pub fn tip_pose(&self) -> Pose {
        *self.bodies[self.peg].position()
    }

    /// Drives the coupling from the commanded tip pose `from` to `to` over
    /// one control period (linear/slerp interpolation per physics step) and
    /// returns the contact wrench averaged over the period.
    pub fn advance(&mut self, from: &Pose, to: &Pose) -> Measurement {
        let dt = self.params.dt;
        let flange_from = from.transform_point(self.flange_local);
        let flange_to = to.transform_point(self.flange_local);
        let target_linvel = (flange_to - flange_from) / self.control_period;
        let target_angvel = (to.rotation * from.rotation.inverse()).to_scaled_axis() / self.control_period;
        let mut impulse = Vector::ZERO;
        let mut angular_impulse = Vector::ZERO;
        for k in 1..=self.substeps {
            let s = k as f64 / self.substeps as f64;
            let target_flange = flange_from.lerp(flange_to, s);
            let target_rotation = from.rotation.slerp(to.rotation, s);
            let (force, torque, v0, w0) = {
                let body = &mut self.bodies[self.peg];
                let g = self.gains;
                // From the pose, not center_of_mass(): rapier refreshes the
                // world COM only inside a step, so it is stale before the first.
                let com = body.position().transform_point(self.flange_local);
                let (v0, w0) = (body.linvel(), body.angvel());
                // Backward-Euler spring-damper: the k·dt term is the damping an
                // implicit step adds, which keeps stiff couplings stable.
                let force = -g.k_lin * (com - target_flange) - (g.c_lin + g.k_lin * dt) * (v0 - target_linvel);
                let error = (*body.rotation() * target_rotation.inverse()).to_scaled_axis();
                let torque = -g.k_rot * error - (g.c_rot + g.k_rot * dt) * (w0 - target_angvel);
                body.reset_forces(false);
                body.reset_torques(false);
                body.add_force(force, false);
                body.add_torque(torque, false);
                (force, torque, v0, w0)
            };
            self.step_physics();
            if self.in_contact() {
                // Momentum balance over the step (no gravity: the robot
                // compensates it and the sensor is tared): what changed the
                // peg's momentum beyond the coupling is the contact.
                let body = &self.bodies[self.peg];
                impulse += self.mass * (body.linvel() - v0) - force * dt;
                angular_impulse += self.inertia * (body.angvel() - w0) - torque * dt;
            }
        }
        let to_newton = 1.0 / (self.control_period * INTERNAL_PER_NEWTON);
        Measurement {
            force_n: (impulse * to_newton).to_array(),
            moment_nmm: (angular_impulse * to_newton).to_array(),
        }
    }

    fn step_physics(&mut self) {
        self.pipeline.step(
            Vector::ZERO,
            &self.params,
            &mut self.islands,
            &mut self.broad_phase,
            &mut self.narrow_phase,
            &mut self.bodies,
            &mut self.colliders,
            &mut self.impulse_joints,
            &mut self.multibody_joints,
            &mut self.soft_bodies,
            &mut self.ccd,
            &(),
            &(),
        );
    }

    /// Whether any contact point between peg and hole is active.
    fn in_contact(&self) -> bool {
        self.narrow_phase.contact_pairs_with(self.peg_collider).any(|pair| pair.has_any_active_contact())
    }

    /// The deepest penetration of the peg into the hole block, mm (0 when
    /// apart), by parry's exact contact query on the current poses.
    pub fn penetration_mm(&self) -> f64 {
        let peg = &self.colliders[self.peg_collider];
        self.hole_colliders
            .iter()
            .filter_map(|&h| {
                let wall = &self.colliders[h];
                query::contact(peg.position(), peg.shape(), wall.position(), wall.shape(), 0.0).ok().flatten()
            })
            .map(|contact| (-contact.dist).max(0.0))
            .fold(0.0, f64::max)
    }
}

/// The peg: a square prism from z = 0 (tip) to z = length, its bottom edges
/// cut by a 45° chamfer (a convex hull), or a plain cuboid without one.
fn peg_shape(cfg: &PegConfig) -> ColliderBuilder {
    let g = &cfg.geometry;
    let (h, len, c) = (g.peg_side_mm / 2.0, g.peg_length_mm, g.peg_chamfer_mm);
    if c == 0.0 {
        return ColliderBuilder::cuboid(h, h, len / 2.0).translation(Vector::new(0.0, 0.0, len / 2.0));
    }
    let mut points = Vec::with_capacity(12);
    for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        points.push(Vector::new(sx * (h - c), sy * (h - c), 0.0));
        points.push(Vector::new(sx * h, sy * h, c));
        points.push(Vector::new(sx * h, sy * h, len));
    }
    // Twelve distinct points of a non-degenerate prism always have a hull.
    ColliderBuilder::convex_hull(&points).expect("chamfered peg hull")
}

/// The block around the hole: four walls and a floor. Walls are cuboids, or
/// convex hulls with their inner top edge cut by the hole chamfer.
fn hole_shapes(cfg: &PegConfig) -> Vec<ColliderBuilder> {
    let g = &cfg.geometry;
    let (h, w, d, c) = (g.hole_side_mm / 2.0, g.wall_mm, g.hole_depth_mm, g.hole_chamfer_mm);
    let outer = h + w;
    let mut shapes = Vec::with_capacity(5);
    // Walls on +x and −x span the full outer width; walls on ±y fill between.
    for sign in [1.0, -1.0] {
        shapes.push(wall(c, [h, outer], [-outer, outer], d, sign, false));
        shapes.push(wall(c, [h, outer], [-h, h], d, sign, true));
    }
    shapes.push(ColliderBuilder::cuboid(outer, outer, w / 2.0).translation(Vector::new(0.0, 0.0, -d - w / 2.0)));
    shapes
}

/// One wall: `across` is its extent away from the hole axis (inner face at
/// across[0]), `along` its extent along the hole side, on the side `sign`;
/// `swap` puts it on the y axis instead of x.
fn wall(chamfer: f64, across: [f64; 2], along: [f64; 2], depth: f64, sign: f64, swap: bool) -> ColliderBuilder {
    let place = |a: f64, b: f64, z: f64| if swap { Vector::new(b, sign * a, z) } else { Vector::new(sign * a, b, z) };
    if chamfer == 0.0 {
        let centre = place((across[0] + across[1]) / 2.0, (along[0] + along[1]) / 2.0, -depth / 2.0);
        let (ha, hb) = ((across[1] - across[0]) / 2.0, (along[1] - along[0]) / 2.0);
        let (hx, hy) = if swap { (hb, ha) } else { (ha, hb) };
        return ColliderBuilder::cuboid(hx, hy, depth / 2.0).translation(centre);
    }
    let mut points = Vec::with_capacity(12);
    for b in along {
        points.push(place(across[1], b, 0.0));
        points.push(place(across[1], b, -depth));
        points.push(place(across[0], b, -depth));
        // The bevel replaces the inner top edge by two edges.
        points.push(place(across[0], b, -chamfer));
        points.push(place(across[0] + chamfer, b, 0.0));
    }
    ColliderBuilder::convex_hull(&points).expect("chamfered wall hull")
}

/// A tip pose from a position (mm) and XYZ Euler angles (degrees).
pub fn pose_from(position: [f64; 3], angles_deg: [f64; 3]) -> Pose {
    let [a, b, c] = angles_deg.map(f64::to_radians);
    Pose::from_parts(Vector::from_array(position), Rotation::from_euler(rapier3d_f64::glamx::EulerRot::XYZ, a, b, c))
}

/// XYZ Euler angles of a rotation, degrees.
pub fn angles_deg(rotation: &Rotation) -> [f64; 3] {
    let (a, b, c) = rotation.to_euler(rapier3d_f64::glamx::EulerRot::XYZ);
    [a.to_degrees(), b.to_degrees(), c.to_degrees()]
}
