//! Reading the holding force through friction at a vertex: the rounds of stick bands and the
//! constraints they give, the last check, the growing push toward the vertex, and the strokes.

use super::*;

impl Calibration {
    /// The ramp of a band measurement along the unit `direction` at a vertex: steady at the
    /// rate that crosses the friction band measured at X_C in `CROSSING_TIME` or moves a
    /// frictionless handle by a slip in `DETECT_TIME`, whichever is faster, over twice the band
    /// (and the slip's force), growing beyond. Off the axes, the axes' stiffness and band are
    /// weighted by the direction's squared components.
    pub(super) fn band_ramp(&self, direction: &Vector3<f64>) -> Ramp {
        let weights = direction.component_mul(direction);
        let stiffness = weights.dot(&self.gains.stiffness) * self.gain_scale;
        let slip_force = stiffness * self.slip;
        let width = 2.0 * weights.dot(&self.initial.friction);
        let rate = (slip_force / DETECT_TIME).max(width / CROSSING_TIME);
        Ramp {
            rate,
            steady: 2.0 * (width + 4.0 * slip_force),
            growth: RAMP_GROWTH,
            limit: self.push_limit(),
        }
    }

    /// Band `k` of a round, starting at time `t`: along the axis k while the normals are the
    /// axes, else along the direction that changes the force on the k-th pair of faces only
    /// (the dual basis of the normals: for joint friction, the force that loads one joint),
    /// so that its chord leaves the stick region through those two faces wherever it starts.
    pub(super) fn band_probe(&self, k: usize, t: f64) -> BandProbe {
        let rows = Matrix3::from_rows(&self.normals.map(|n| n.transpose()));
        let direction = rows
            .try_inverse()
            .and_then(|dual| dual.column(k).try_normalize(1e-12))
            .unwrap_or_else(|| axis(k));
        BandProbe::new(
            k,
            direction,
            self.band_ramp(&direction),
            self.slip,
            self.still,
            t,
        )
    }

    /// The first axis after `a` (all of them: from `None`) with friction, if any.
    pub(super) fn next_band_axis(&self, after: Option<usize>) -> Option<usize> {
        let from = after.map_or(0, |a| a + 1);
        (from..3).find(|&a| self.friction_kind[a] != Friction::None)
    }

    /// A round of band measurements along the axes with friction: x, y, then z.
    pub(super) fn start_round(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        let Some(a) = self.next_band_axis(None) else {
            // No friction anywhere: the force applied at this rest is the load. It is taken at
            // the second rest near the vertex, which follows a correction too small to leave a
            // transient (the paper's "n_M samples within ε_M", read as twice in a row).
            let vertex = self.plan.path[self.vertex];
            let error = (vertex.position - self.rest).norm();
            if self.near_rests < 2 {
                return self.update(s, self.estimate, error);
            }
            self.measured_at = self.rest;
            return self.vertex_done(s, vertex, error);
        };
        self.phase = Phase::Band {
            probe: self.band_probe(a, t),
            round_start: self.estimate,
            anchor: self.smoothed,
        };
        ControlOutput::force(self.still_force(&self.smoothed, s, &self.estimate))
    }

    /// The stick band at the vertex, axis by axis: F̂ along the axis becomes the band's middle.
    /// After z, the round is over: the vertex is done once a round changes F̂ by less than a
    /// quarter of the band (or after `MAX_ROUNDS`); otherwise the handle settles again (it may
    /// have moved under the new force) and another round follows. A direction the handle does
    /// not move along under the whole push is blocked: the vertex is unreachable.
    pub(super) fn band(
        &mut self,
        s: &DeviceState,
        mut probe: BandProbe,
        round_start: Vector3<f64>,
        anchor: Vector3<f64>,
    ) -> ControlOutput {
        let t = s.time;
        let vertex = self.plan.path[self.vertex];
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let feedforward = self.estimate + probe.direction() * probe.offset(t);
        let force = self.still_force(&anchor, s, &feedforward);
        match probe.observe(s, &self.smoothed, &force) {
            Step::Running => {
                self.phase = Phase::Band {
                    probe,
                    round_start,
                    anchor,
                };
                ControlOutput::force(force)
            }
            Step::Blocked { .. } => self.give_up(s, (vertex.position - self.rest).norm(), None),
            Step::Done(band) => {
                let k = probe.index();
                // F̂ moves along the band's direction until its load on the band's pair of faces
                // is the band's middle; the direction loads no other pair.
                let (n, d) = (self.normals[k], band.direction);
                self.estimate += d * (n.dot(&(band.midpoint() - self.estimate)) / n.dot(&d));
                self.faces[k] = band.half_width() * n.dot(&d);
                self.strict[k] = band.constraint();
                let loose = band.loose_constraint();
                // Joint friction: from the end of this round on, learn its normals.
                self.joint_friction |=
                    loose.0.dot(&d) < ALONG_PUSH && !self.friction_kind.contains(&Friction::None);
                // Along the axes a ball's chord crossed off its centre still gives a constraint.
                self.constraints[k] = if self.learn_normals {
                    self.strict[k]
                } else {
                    Some(loose)
                };
                self.slips[k] = band.slips();
                self.band_at[k] = band.at;
                if let Some(next) = self.next_band_axis(Some(k)) {
                    self.phase = Phase::Band {
                        probe: self.band_probe(next, t),
                        round_start,
                        anchor: self.smoothed,
                    };
                    return ControlOutput::force(force);
                }
                self.round_done(s, vertex, round_start, force)
            }
        }
    }

    /// A round is over: the vertex is done once a round changed F̂ by little (the chords the
    /// bands were measured along then pass through the band's middle), or after `MAX_ROUNDS`;
    /// otherwise another round follows at once, or, if the handle has crept off the vertex,
    /// after it settles again.
    pub(super) fn round_done(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        round_start: Vector3<f64>,
        force: Vector3<f64>,
    ) -> ControlOutput {
        self.rounds += 1;
        self.iteration += 1;
        let consistent = self.solve_constraints();
        if self.joint_friction && !self.learn_normals {
            // The round that showed joint friction brought F̂ nearer the centre along the
            // axes; the vertex is measured afresh along the normals its slips teach.
            self.learn_normals = true;
            self.rounds = 0;
            self.earlier_rounds = (Vector3::zeros(), Vector3::zeros(), 0);
            self.learn_normals();
            return self.start_round(s);
        }
        if self.learn_normals {
            self.learn_normals();
        }
        self.band_friction = self.axis_friction();
        let change = self.estimate - round_start;
        // While the normals are still being learnt, a round whose chords did not all cross one
        // pair of faces is no measurement of the same thing as the next one.
        let measured = consistent || !self.learn_normals;
        let settled = measured
            && (0..3).all(|k| {
                self.friction_kind[k] == Friction::None
                    || self.normals[k].dot(&change).abs()
                        <= ROUND_SHARE * self.faces[k] + FORCE_TOLERANCE
            });
        let error = (vertex.position - self.rest).norm();
        self.emit(CalibrationEvent::Iteration {
            vertex: self.vertex,
            iteration: self.iteration,
            force: self.estimate,
            error,
        });
        // A vertex whose last round was no clean measurement gets one more while it has time.
        let more = self.rounds < MAX_ROUNDS
            || (!measured
                && self.rounds < MAX_ROUNDS + 1
                && s.time - self.vertex_start < 0.5 * self.params.vertex_timeout);
        if (settled && self.rounds >= MIN_ROUNDS) || !more {
            // The rounds measured the same band independently: their mean shrinks what the
            // slips' timing and the position noise scatter.
            // A last round that was no such measurement is left out if there are others.
            let (sum, at, count) = self.earlier_rounds;
            let here = self.round_at();
            (self.estimate, self.measured_at) = if measured || count == 0 {
                let n = f64::from(count + 1);
                ((sum + self.estimate) / n, (at + here) / n)
            } else {
                (sum / f64::from(count), at / f64::from(count))
            };
            if !self.friction_kind.contains(&Friction::Slight) {
                return self.stroke(s, vertex, StrokeRun::first(error, None));
            }
            self.detector.reset();
            self.phase = Phase::Check {
                anchor: self.smoothed,
                since: s.time,
            };
            return ControlOutput::force(force);
        }
        if self.iteration >= self.params.max_iterations {
            let failure = CalibrationFailure::TooManyIterations {
                vertex,
                iterations: self.iteration,
            };
            return self.give_up(s, (vertex.position - s.position).norm(), Some(failure));
        }
        // The slips of a round move the handle a little; a new estimate may move it a little
        // more: measure again where it is unless it has gone far.
        let offset = vertex.position - self.smoothed;
        if (0..3).all(|a| offset[a].abs() <= ROUND_REACH * self.reach_tolerance(a)) {
            if measured {
                self.earlier_rounds.0 += self.estimate;
                self.earlier_rounds.1 += self.round_at();
                self.earlier_rounds.2 += 1;
            }
            return self.start_round(s);
        }
        self.settle_from(s.time);
        ControlOutput::force(force)
    }

    /// Where this round's bands were measured, on average, m.
    pub(super) fn round_at(&self) -> Vector3<f64> {
        let bands = (0..3).filter(|&a| self.friction_kind[a] != Friction::None);
        let (sum, count) = bands.fold((Vector3::zeros(), 0.0), |(sum, n), a| {
            (sum + self.band_at[a], n + 1.0)
        });
        if count > 0.0 {
            sum / count
        } else {
            self.rest
        }
    }

    /// The check (see [`Phase::Check`]): along each axis the handle moved on by more than a
    /// slip, the force it rests under replaces the band's middle.
    pub(super) fn check(
        &mut self,
        s: &DeviceState,
        anchor: Vector3<f64>,
        since: f64,
    ) -> ControlOutput {
        let t = s.time;
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let force = self.hold_force(&anchor, s, &self.estimate);
        if t - since < self.settle_time {
            return ControlOutput::force(force);
        }
        let Some(rest) = self.detector.push(&s.position) else {
            return ControlOutput::force(force);
        };
        let stiffness = self.gains.scaled(self.gain_scale).stiffness;
        // Beyond the noise of the anchor (a mean of 8 samples) and of the rest (of n_M), or half
        // an encoder step, whichever is more.
        let moved = (3.0 * self.initial.noise * (0.125 + 1.0 / self.params.n_m as f64).sqrt())
            .max(0.5 * self.initial.step);
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Slight && (rest[a] - anchor[a]).abs() > moved {
                self.estimate[a] += stiffness[a] * (anchor[a] - rest[a]);
            }
        }
        let vertex = self.plan.path[self.vertex];
        self.stroke(
            s,
            vertex,
            StrokeRun::first((vertex.position - rest).norm(), None),
        )
    }

    /// With friction at the vertex, the bands have brought F̂ within a few millinewtons; strokes
    /// through the vertex measure it to one ([`Strokes`]), following [`Phase::Strokes`].
    pub(super) fn stroke(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        run: StrokeRun,
    ) -> ControlOutput {
        let strokes = self
            .params
            .arm
            .and_then(|arm| {
                Strokes::along_the_arm(Stroke::MEASURE_ALONG_THE_ARM, &arm, vertex.position, s.time)
            })
            .unwrap_or_else(|| {
                if self.joint_friction {
                    Strokes::through_every_joint(Stroke::MEASURE, vertex.position, s.time)
                } else {
                    Strokes::along_a_diagonal(
                        Stroke::MEASURE_ALONG_THE_ARM,
                        vertex.position,
                        s.time,
                    )
                }
            });
        self.phase = Phase::Strokes { strokes, run };
        ControlOutput::force(self.hold_force(&vertex.position, s, &self.estimate))
    }

    /// The hold on a stroke's set point at full gains (a backed-off hold would trail it further),
    /// damping the velocity relative to the set point's; along axes where friction dominates,
    /// only `STROKE_DAMPING` of it.
    pub(super) fn stroke_force(&self, strokes: &Strokes, s: &DeviceState) -> Vector3<f64> {
        let (target, velocity) = strokes.set_point(s.time);
        let mut relative = *s;
        relative.velocity -= velocity;
        let mut gains = self.gains;
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Dominant {
                gains.damping[a] *= STROKE_DAMPING;
            }
        }
        gains.pd_force(&target, &relative, &self.estimate)
    }

    /// The force of the hold's spring, at full gains, on the handle (its smoothed position) off
    /// `target`, N.
    pub(super) fn spring(&self, target: &Vector3<f64>) -> Vector3<f64> {
        self.gains
            .stiffness
            .component_mul(&(target - self.smoothed))
    }

    /// [`Self::spring`] when it keeps the handle off `target` with more than strokes tolerate in
    /// their feedforward (`STROKE_REPEAT`), but no more than the push limit: friction yields to
    /// that much, so a handle held off by more is on something else (a stop), or F̂ is far off,
    /// and the force there says nothing about the load. It is read as the strokes' home leg
    /// ends, without waiting for the handle to come to rest (requiring rest there skipped the
    /// retry the delta at 0.02 N at the handle needs).
    pub(super) fn held_off(&self, target: &Vector3<f64>) -> Option<Vector3<f64>> {
        let spring = self.spring(target);
        (STROKE_REPEAT..=self.push_limit())
            .contains(&spring.norm())
            .then_some(spring)
    }

    pub(super) fn strokes(
        &mut self,
        s: &DeviceState,
        mut strokes: Strokes,
        run: StrokeRun,
    ) -> ControlOutput {
        let force = self.stroke_force(&strokes, s);
        let vertex = self.plan.path[self.vertex];
        match strokes.observe(s, &force) {
            Step::Running => {
                self.phase = Phase::Strokes { strokes, run };
                ControlOutput::force(force)
            }
            Step::Done(stroked) => {
                let arm_fit = self.arm_fit.as_ref();
                let stroked = stroked.less_curvature(|x| arm_fit.and_then(|fit| fit.predict(x)));
                let change = (stroked.force - self.estimate).norm();
                self.estimate = stroked.force;
                self.measured_at = stroked.at;
                self.iteration += 1;
                let again =
                    STROKE_REPEAT.max(self.params.strokes_again_share * stroked.force.norm());
                if change > again && run.repeat {
                    // A hold that far off the load kept the handle off the middle of the
                    // windows: measure again from what the strokes found.
                    let again = StrokeRun {
                        repeat: false,
                        bands_force: None,
                        ..run
                    };
                    return self.stroke(s, vertex, again);
                }
                self.emit(CalibrationEvent::Iteration {
                    vertex: self.vertex,
                    iteration: self.iteration,
                    force: self.estimate,
                    error: run.error,
                });
                self.vertex_done(s, vertex, run.error)
            }
            // Held off by more than friction yields to: F̂ is no measurement of the load (the
            // delta at 0.02 N, unit 1, seed 3: rounds of bands that disagreed left it 2.8 N
            // off, 264 % of the holding force) or a stop is within a stroke of the vertex.
            // Either way the vertex is measured again from beside it.
            Step::Blocked { .. } if self.spring(&vertex.position).norm() > self.push_limit() => {
                let off = (vertex.position - self.smoothed).norm();
                let failure = CalibrationFailure::HeldOff {
                    vertex,
                    offset_mm: off * 1e3,
                };
                self.give_up(s, off, Some(failure))
            }
            // The hold kept the handle off the windows: where it rests now, the force that holds
            // it there is the holding force to within the friction, whatever F̂ was. An F̂ that
            // far off (rounds whose bands misread a ball of friction at the handle as a joint's
            // faces) is replaced by that force and the strokes run once more, keeping the bands'
            // F̂; a stop stays a stop, and blocks them again.
            Step::Blocked { .. } if run.repeat && run.bands_force.is_none() => {
                match self.held_off(&vertex.position) {
                    Some(spring) => {
                        let retry = StrokeRun {
                            bands_force: Some(self.estimate),
                            ..run
                        };
                        self.estimate += spring;
                        self.stroke(s, vertex, retry)
                    }
                    None => self.blocked(s, vertex, run),
                }
            }
            Step::Blocked { .. } => self.blocked(s, vertex, run),
        }
    }

    /// Something within a stroke's reach of the vertex stops the handle: the bands'
    /// measurement stands, if they finished.
    pub(super) fn blocked(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        run: StrokeRun,
    ) -> ControlOutput {
        if let Some(bands_force) = run.bands_force {
            self.estimate = bands_force;
        }
        match run.late {
            Some(failure) => {
                let distance = (vertex.position - s.position).norm();
                self.give_up(s, distance, Some(failure))
            }
            None => self.vertex_done(s, vertex, run.error),
        }
    }

    /// F̂ from the round's bands: the force c with n·c = b for each band's constraint
    /// ([`Band::constraint`](crate::control::calibration::probe::Band::constraint)) and, along
    /// axes without friction, c = F̂ there. A band without a constraint (its chord left through
    /// the faces of two joints), or whose constraint repeats an earlier band's pair of faces,
    /// keeps its pair's normal n and the middle its update put into F̂ (n·c = n·F̂). Where every axis has friction, the constraints' normals become the
    /// normals the next round's directions follow. Normals too close to coplanar change
    /// nothing. True when every band gave a constraint of its own.
    pub(super) fn solve_constraints(&mut self) -> bool {
        let mut rows = [(Vector3::zeros(), 0.0); 3];
        let mut consistent = true;
        for k in 0..3 {
            if self.friction_kind[k] == Friction::None {
                rows[k] = (axis(k), self.estimate[k]);
                continue;
            }
            let own = self.constraints[k].filter(|(n, _)| {
                rows[..k]
                    .iter()
                    .all(|(other, _)| n.dot(other).abs() < SAME_FACES)
            });
            consistent &= own.is_some();
            let n = self.normals[k];
            rows[k] = own.unwrap_or((n, n.dot(&self.estimate)));
        }
        let n = Matrix3::from_rows(&rows.map(|(n, _)| n.transpose()));
        if n.determinant().abs() < MIN_CONSTRAINT_VOLUME {
            return false;
        }
        let Some(c) = n.lu().solve(&Vector3::from(rows.map(|(_, b)| b))) else {
            return false;
        };
        self.estimate = c;
        consistent
    }

    /// The normals the next round's bands follow, from this round's: the first three that span
    /// space (20° apart, then a volume of at least `MIN_CONSTRAINT_VOLUME`) of the constraints'
    /// normals, then the directions of single slips seen twice (a joint that gave alone slips
    /// along the normal of the face it left through; a chord that leaves through the faces of
    /// two joints still shows one of them), then the normals followed so far. The next round's bands, along their dual directions, then load one
    /// joint each, and their chords cross one pair of faces each.
    pub(super) fn learn_normals(&mut self) {
        let constraints = self.strict.map(|c| c.map(|(n, _)| n));
        let slips: [Option<Vector3<f64>>; 6] = [0, 1, 2, 3, 4, 5].map(|i| self.slips[i / 2][i % 2]);
        // A slip counts where another slip or a constraint of the round went its way too (one
        // joint giving again); two joints giving together rarely mix the same way twice.
        let repeated = |i: usize, u: &Vector3<f64>| {
            let others = slips
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, v)| v);
            others
                .chain(constraints.iter())
                .flatten()
                .any(|v| u.dot(v).abs() >= SAME_FACES)
        };
        let candidates = constraints
            .into_iter()
            .chain(
                slips
                    .iter()
                    .enumerate()
                    .map(|(i, u)| u.filter(|u| repeated(i, u))),
            )
            .chain(self.normals.map(Some))
            .flatten();
        let mut learned = [Vector3::zeros(); 3];
        let mut count = 0;
        for n in candidates {
            let fresh = match count {
                0 => true,
                1 => n.dot(&learned[0]).abs() < SAME_FACES,
                2 => {
                    let rows = Matrix3::from_rows(&[
                        learned[0].transpose(),
                        learned[1].transpose(),
                        n.transpose(),
                    ]);
                    rows.determinant().abs() >= MIN_CONSTRAINT_VOLUME
                }
                _ => false,
            };
            if fresh {
                learned[count] = n;
                count += 1;
            }
        }
        let volume = Matrix3::from_rows(&learned.map(|n| n.transpose())).determinant();
        if count == 3 && volume.abs() >= MIN_CONSTRAINT_VOLUME {
            self.normals = learned;
        }
    }

    /// The stick region's half-width along each axis through its centre, N: where the axis
    /// first meets a pair of faces (for faces normal to the axes, their half-distance).
    pub(super) fn axis_friction(&self) -> Vector3<f64> {
        Vector3::from_fn(|a, _| {
            (0..3)
                .filter(|&k| self.normals[k][a].abs() > 1e-9)
                .map(|k| self.faces[k] / self.normals[k][a].abs())
                .fold(f64::INFINITY, f64::min)
        })
        .map(|w| if w.is_finite() { w } else { 0.0 })
    }

    /// The push toward the vertex: if the handle moves, it was friction (F̂ keeps the push,
    /// and the handle settles again); if it does not under the whole push, the vertex is
    /// unreachable.
    pub(super) fn push(&mut self, s: &DeviceState, mut push: Push) -> ControlOutput {
        let t = s.time;
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let vertex = self.plan.path[self.vertex].position;
        let extra = push.direction * push.force(t);
        let force = self.hold_force(&vertex, s, &(self.estimate + extra));
        match push.observe(s) {
            Step::Running => {
                self.phase = Phase::Push(push);
                ControlOutput::force(force)
            }
            Step::Done(_) => {
                self.estimate += extra;
                self.settle_from(t);
                ControlOutput::force(force)
            }
            Step::Blocked { .. } => self.give_up(s, (vertex - s.position).norm(), None),
        }
    }
}
