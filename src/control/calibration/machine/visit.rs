//! Each vertex in turn: the move to it (from a prediction where friction dominates), the rests
//! near it and the updates of F̂ (Eqs. 13–14), the vertex done, retried from beside it, or
//! skipped; the next vertex, or the exploration's probes.

use super::*;

impl Calibration {
    /// Set off from `from` toward the current vertex, with a fresh vertex record.
    pub(super) fn start_move(&mut self, from: Vector3<f64>, t: f64) {
        let to = self.plan.path[self.vertex].position;
        self.approach = from;
        // With a saved model, the hold starts from the force last measured plus the model's
        // change from there (where the previous hold was measured, or X_C) to the vertex.
        let measured_there =
            self.vertex == 0 || self.results[self.vertex - 1].is_some_and(|r| r.reached);
        if let Some(prior) = self.params.prior.as_ref().filter(|_| measured_there) {
            if let (Some(there), Some(here)) = (prior.expected_at(&to), prior.expected_at(&from)) {
                self.estimate += there - here;
            }
        }
        // An explored grid's path jumps where it skips extrapolated vertices: start from the
        // force of the closest vertex calibrated so far (Eq. 12), not of the last one.
        if self.explorer.is_some() {
            let closest = self
                .results
                .iter()
                .flatten()
                .filter(|r| r.reached)
                .min_by(|a, b| {
                    let d = |r: &VertexResult| (r.vertex.position - to).norm();
                    d(a).total_cmp(&d(b))
                });
            if let Some(r) = closest {
                self.estimate = r.force;
            }
        }
        let duration = self.glide(from, to, t).duration;
        let prediction = (self.params.predict_vertices
            && self.explorer.is_none()
            && self.params.prior.is_none()
            && self.friction_kind.contains(&Friction::Dominant)
            && self.initial.friction.max() >= STROKES_AT_ONCE)
            .then(|| self.predicted_force(&to))
            .flatten();
        // An explored workspace may end short of a vertex the map holds: move no faster than
        // the walk's moves (minimum-jerk peak speed 1.875 d / T), so a stop met on the way is
        // met slowly; along an edge the walk travelled, as fast as its returns. The extra time
        // does not count against the vertex's time limit.
        let walked = self
            .explorer
            .as_ref()
            .is_some_and(|e| e.map().walked(&from, &to));
        let slowed = match (&self.explorer, walked) {
            (Some(_), true) => duration.max(1.875 * (to - from).norm() / explore::RETURN_SPEED),
            (Some(_), false) => duration.max(1.875 * (to - from).norm() / explore::PROBE_SPEED),
            (None, _) => duration,
        };
        self.phase = Phase::Move {
            path: Glide {
                from,
                to,
                start: t,
                duration: slowed,
            },
            walked,
            then: [None; 2],
        };
        self.vertex_start = t + (slowed - duration);
        self.vertex_began = t;
        self.fresh_attempt();
        if let Some(force) = prediction {
            self.estimate = force;
            self.strokes_at_once = true;
        }
        self.emit(CalibrationEvent::VertexStarted {
            vertex: self.vertex,
            of: self.plan.path.len(),
            at: self.plan.path[self.vertex],
            elapsed: self.elapsed(),
        });
    }

    /// A vertex's count of updates, rounds and rests starts afresh (a new vertex, or the second
    /// attempt at one).
    pub(super) fn fresh_attempt(&mut self) {
        self.iteration = 0;
        self.rounds = 0;
        self.previous_offset = None;
        self.near_rests = 0;
        self.one_sided = None;
        self.band_friction = Vector3::zeros();
        // With a saved model every hold under friction starts from its force (`start_move`).
        self.strokes_at_once = self.params.prior.is_some() && self.next_band_axis(None).is_some();
        self.detector = self.vertex_detector();
    }

    /// The holding force at `to` predicted from the vertices measured so far: by the arm's
    /// gravity fitted to them where the profile gives an arm and the fit explains them
    /// ([`ArmPrediction`]: 0.1–10 mN off on the simulated linkages, once three are measured),
    /// else by three of them that make a parallelogram with it ([`Self::force_from_neighbours`]:
    /// 10–50 mN off on the PHANToM, up to 0.4 N on the delta).
    pub(super) fn predicted_force(&self, to: &Vector3<f64>) -> Option<Vector3<f64>> {
        self.arm_fit
            .as_ref()
            .and_then(|fit| fit.predict(to))
            .or_else(|| self.force_from_neighbours(to))
    }

    /// The holding force at `to` predicted from three vertices measured so far that make a
    /// parallelogram with it, to = a + b − c (a = b: a straight line through c and a): F(a) +
    /// F(b) − F(c), exact for a field linear over the stencil; the most compact such stencil.
    /// None while no three do. A stencil within [`PREDICT_REACH`] has every vertex within two
    /// spacings of `to` along each axis: those are set out on a 5 × 5 × 5 table of offsets
    /// first, so the search costs the same on any grid (no allocation: it runs on the servo
    /// thread).
    pub(super) fn force_from_neighbours(&self, to: &Vector3<f64>) -> Option<Vector3<f64>> {
        const SIDE: i32 = 5;
        let spacing = self.params.spacing;
        // The offset of `x` from `to` in whole spacings, -2..=2 along each axis, if it is one.
        let cell = |x: &Vector3<f64>| -> Option<[i32; 3]> {
            let steps = (x - to) / spacing;
            let rounded = steps.map(f64::round);
            let inside = rounded.iter().all(|k| k.abs() <= 2.0);
            ((steps - rounded).norm() < PREDICT_MATCH && inside)
                .then(|| [0, 1, 2].map(|a| rounded[a] as i32))
        };
        let slot =
            |o: [i32; 3]| ((o[0] + 2) * SIDE * SIDE + (o[1] + 2) * SIDE + (o[2] + 2)) as usize;
        let mut table = [None; (SIDE * SIDE * SIDE) as usize];
        let mut near = [[0; 3]; (SIDE * SIDE * SIDE) as usize];
        let mut count = 0;
        for r in self.results.iter().flatten().filter(|r| r.reached) {
            if let Some(o) = cell(&r.vertex.position) {
                if table[slot(o)].is_none() {
                    near[count] = o;
                    count += 1;
                }
                table[slot(o)] = Some(r.force);
            }
        }
        let near = &near[..count];
        let length = |o: [i32; 3]| f64::from(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt();
        let mut best: Option<(f64, Vector3<f64>)> = None;
        for &a in near {
            for &c in near {
                // to = a + b − c, with `to` at the origin of the offsets: b = c − a.
                let b = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                if a == c || b.iter().any(|k| k.abs() > 2) {
                    continue;
                }
                let (Some(force_a), Some(force_b), Some(force_c)) =
                    (table[slot(a)], table[slot(b)], table[slot(c)])
                else {
                    continue;
                };
                let spread = length(a) + length(b) + length(c);
                if spread <= PREDICT_REACH && best.is_none_or(|(s, _)| spread < s) {
                    best = Some((spread, force_a + force_b - force_c));
                }
            }
        }
        best.map(|(_, force)| force)
    }

    /// The steady-state test at vertices: n_M samples within ε_M, window means agreeing within
    /// what the position noise allows (at most ε_M/10): the closer a hold is to rest, the
    /// closer the force it applies is to the load.
    pub(super) fn vertex_detector(&self) -> SteadyState {
        let n = self.params.n_m;
        let eps = self.params.eps_m;
        let creep = (CREEP_SIGMAS * self.initial.noise * (2.0 / n as f64).sqrt())
            .max(MIN_CREEP)
            .min(eps / 10.0);
        SteadyState::with_creep(n, eps, creep)
    }

    /// The hold toward `target`: the PD (backed off by `gain_scale`) plus the gravity term
    /// `feedforward` (Eq. 10 with the force estimate as a vector).
    pub(super) fn hold_force(
        &self,
        target: &Vector3<f64>,
        s: &DeviceState,
        feedforward: &Vector3<f64>,
    ) -> Vector3<f64> {
        self.gains
            .scaled(self.gain_scale)
            .pd_force(target, s, feedforward)
    }

    /// The hold at rest: like [`Self::hold_force`], without velocity feedback along axes whose
    /// friction dissipates more than the feedback would (its noise would shake a stuck handle),
    /// and pulling on the smoothed position there, while the handle is at rest; once it moves
    /// faster than `RINGING_SPEED`, the full hold, so that it cannot ring up.
    pub(super) fn still_force(
        &self,
        target: &Vector3<f64>,
        s: &DeviceState,
        feedforward: &Vector3<f64>,
    ) -> Vector3<f64> {
        let mut gains = self.gains.scaled(self.gain_scale);
        let mut still = *s;
        let at_rest = s.velocity.norm() < RINGING_SPEED;
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Dominant && at_rest {
                gains.damping[a] = 0.0;
                still.position[a] = self.smoothed[a];
            }
        }
        gains.pd_force(target, &still, feedforward)
    }

    /// Move (§3.2): the PD (with the force estimate so far) follows the glide to the vertex,
    /// then holds it.
    pub(super) fn move_to_vertex(
        &mut self,
        s: &DeviceState,
        path: Glide,
        walked: bool,
        then: [Option<Vector3<f64>>; 2],
    ) -> ControlOutput {
        // In an explored workspace, a handle that stops following the move has met a stop the
        // map did not know: the vertex is out of reach, and the hold stays where the handle is.
        // Along an edge the walk travelled nothing is in the way, and the faster move lags more.
        if self.explorer.is_some()
            && !walked
            && (path.at(s.time) - s.position).norm() > explore::CONTACT_LAG
        {
            return self.skip(s, (path.to - s.position).norm(), None);
        }
        if path.progress(s.time) >= 1.0 {
            match then {
                [Some(next), after] => {
                    self.phase = Phase::Move {
                        path: self.glide(path.to, next, s.time),
                        walked,
                        then: [after, None],
                    };
                }
                // F̂ predicted under friction: the strokes measure at once (and again if they
                // moved F̂ far), with no rests or bands first.
                _ if self.strokes_at_once => {
                    let vertex = self.plan.path[self.vertex];
                    let error = (vertex.position - s.position).norm();
                    return self.stroke(s, vertex, StrokeRun::first(error, None));
                }
                _ => self.settle_from(s.time),
            }
        }
        ControlOutput::force(self.hold_force(&path.at(s.time), s, &self.estimate))
    }

    /// Settle from time `t`: a fresh steady-state test after the settle time.
    pub(super) fn settle_from(&mut self, t: f64) {
        self.detector.reset();
        self.phase = Phase::Settle { since: t };
    }

    /// `vertex_timeout` has passed at the current vertex. With friction, a hold may keep coming
    /// to rest off the vertex, creep, or its bands may not agree in time: strokes through the
    /// vertex measure its force wherever the hold left the handle, and the vertex fails only if
    /// something stops them. Without friction it fails at once.
    pub(super) fn out_of_time(
        &mut self,
        s: &DeviceState,
        failure: CalibrationFailure,
    ) -> ControlOutput {
        if self
            .friction_kind
            .iter()
            .all(|&kind| kind == Friction::None)
        {
            let distance = (self.plan.path[self.vertex].position - s.position).norm();
            return self.give_up(s, distance, Some(failure));
        }
        let vertex = self.plan.path[self.vertex];
        let error = (vertex.position - self.smoothed).norm();
        // Updates that did not converge may have taken F̂ far off, and a hold that far off the
        // load leaves the handle outside the strokes' windows: start from the last vertex's.
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        self.stroke(s, vertex, StrokeRun::first(error, Some(failure)))
    }

    pub(super) fn vertex_timed_out(&self, t: f64) -> Option<CalibrationFailure> {
        (t - self.vertex_start > self.params.vertex_timeout).then_some(
            CalibrationFailure::VertexTimeout {
                vertex: self.plan.path[self.vertex],
                timeout: self.params.vertex_timeout,
                iterations: self.iteration,
            },
        )
    }

    /// Hold (§3.2): the PD holds the vertex with the force estimate (Eq. 10). Each steady state
    /// after the settle time is a rest to act on; a hold without a steady state backs off its
    /// gains.
    pub(super) fn settle(&mut self, s: &DeviceState, since: f64) -> ControlOutput {
        let t = s.time;
        let vertex = self.plan.path[self.vertex];
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let force = self.hold_force(&vertex.position, s, &self.estimate);
        if t - since < self.settle_time / self.gain_scale.sqrt() {
            return ControlOutput::force(force);
        }
        match self.detector.push(&s.position) {
            Some(rest) => self.at_rest(s, vertex, rest, force),
            None => {
                if t - since > self.settle_time + GAIN_BACKOFF_AFTER
                    && self.gain_scale > MIN_GAIN_SCALE
                {
                    self.back_off(t);
                }
                ControlOutput::force(force)
            }
        }
    }

    /// Halve the PD's gains (not the force estimate): gains built on a mass several times too
    /// large make the hold oscillate through the velocity filter's lag, and no steady state
    /// comes. The next update restores them.
    pub(super) fn back_off(&mut self, t: f64) {
        self.gain_scale *= 0.5;
        self.settle_from(t);
        self.emit(CalibrationEvent::GainsReduced {
            vertex: self.vertex,
            scale: self.gain_scale,
        });
    }

    /// How far from the vertex along axis `a` a rest still counts as reached, m: the friction
    /// band's span of offset a few times over, plus the noise.
    pub(super) fn reach_tolerance(&self, a: usize) -> f64 {
        let stiffness = self.gains.stiffness[a] * self.gain_scale;
        REACH_BANDS * self.initial.friction[a] / stiffness + 3.0 * self.initial.noise + REACH_MARGIN
    }

    /// A rest X̄ at `vertex` X_i. There the hold applies F̂ + K (X_i − X̄), which balances the
    /// load up to the friction. Near the vertex: measure the stick band. Off it: that force
    /// becomes F̂ (the vector form of the signed Eq. 11; the paper's norm loses the sign), and
    /// the hold pulls the handle closer; if the previous update did not bring it closer, push.
    pub(super) fn at_rest(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        rest: Vector3<f64>,
        force: Vector3<f64>,
    ) -> ControlOutput {
        let t = s.time;
        let offset = vertex.position - rest;
        let applied =
            self.estimate + offset.component_mul(&self.gains.scaled(self.gain_scale).stiffness);
        if (0..3).all(|a| offset[a].abs() <= self.reach_tolerance(a)) {
            // The hold now centres on the rest itself: no jump, since F̂ becomes the force it
            // applies there (inside the stick band: the handle rests under it).
            self.one_sided.get_or_insert(applied);
            self.estimate = applied;
            self.rest = rest;
            self.near_rests += 1;
            self.earlier_rounds = (Vector3::zeros(), Vector3::zeros(), 0);
            return self.start_round(s);
        }
        let distance = offset.norm();
        if self
            .previous_offset
            .is_some_and(|previous| distance > PROGRESS * previous)
        {
            let rate = (0..3)
                .map(|a| self.band_ramp(&axis(a)).rate)
                .fold(0.0, f64::max);
            let ramp = Ramp {
                rate,
                steady: 0.0,
                growth: RAMP_GROWTH,
                limit: self.push_limit(),
            };
            self.previous_offset = None;
            self.phase = Phase::Push(Push::new(offset / distance, ramp, self.slip, t));
            return ControlOutput::force(force);
        }
        self.previous_offset = Some(distance);
        self.update(s, applied, distance)
    }

    /// F̂ ← `force`; count it, and give up after `max_iterations`.
    pub(super) fn update(
        &mut self,
        s: &DeviceState,
        force: Vector3<f64>,
        error: f64,
    ) -> ControlOutput {
        self.estimate = force;
        self.gain_scale = 1.0;
        self.iteration += 1;
        self.emit(CalibrationEvent::Iteration {
            vertex: self.vertex,
            iteration: self.iteration,
            force,
            error,
        });
        if self.iteration >= self.params.max_iterations {
            let vertex = self.plan.path[self.vertex];
            let failure = CalibrationFailure::TooManyIterations {
                vertex,
                iterations: self.iteration,
            };
            return self.give_up(s, (vertex.position - s.position).norm(), Some(failure));
        }
        self.settle_from(s.time);
        let vertex = self.plan.path[self.vertex].position;
        ControlOutput::force(self.hold_force(&vertex, s, &self.estimate))
    }

    /// Record the vertex and go on to the next one, which starts from this one's force
    /// (Eqs. 12, 14; already in `estimate`), or finish.
    pub(super) fn vertex_done(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        error: f64,
    ) -> ControlOutput {
        let result = VertexResult {
            vertex,
            mass: 0.0,
            force: self.estimate,
            held_force: self.estimate,
            one_sided_force: self.one_sided.unwrap_or(self.estimate),
            friction: self.band_friction,
            iterations: self.iteration,
            final_error: error,
            measured_at: self.measured_at,
            duration: s.time - self.vertex_began,
            reached: true,
            failure: None,
        };
        self.results[self.vertex] = Some(result);
        if let Some(fit) = &mut self.arm_fit {
            fit.add(&self.measured_at, &self.estimate);
        }
        self.last_good = self.estimate;
        self.last_normals = self.normals;
        let load = self.initial.load;
        let along = if load.norm() > 0.0 {
            load.normalize()
        } else {
            Vector3::z()
        };
        self.emit(CalibrationEvent::VertexDone {
            vertex: self.vertex,
            of: self.plan.path.len(),
            mass: self.estimate.dot(&along) / self.params.g,
            force: self.estimate,
            iterations: self.iteration,
            elapsed: self.elapsed(),
        });
        self.next_vertex(s, vertex.position)
    }

    /// The current vertex could not be measured: the handle did not yield to a push toward it
    /// (`failure` None), or it did not converge (`failure`). The first time, it is approached
    /// again from beside it, from the last vertex's force, with its time and updates afresh: an
    /// obstacle on the straight way, or a hold that rang or crept from one side, need not be in
    /// the way of another. The second time, it is skipped.
    pub(super) fn give_up(
        &mut self,
        s: &DeviceState,
        distance: f64,
        failure: Option<CalibrationFailure>,
    ) -> ControlOutput {
        // An explored workspace's map already knows where the handle can go.
        if self.retried || self.explorer.is_some() {
            return self.skip(s, distance, failure);
        }
        self.retried = true;
        // What a failed attempt's bands learnt may be as wrong as its F̂.
        self.normals = self.last_normals;
        let vertex = self.plan.path[self.vertex];
        let beside = self.beside(&vertex.position, &self.approach);
        self.emit(CalibrationEvent::VertexRetried {
            vertex: self.vertex,
            at: vertex,
            failure,
            beside,
        });
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        // Back to where the first approach began (a point the handle reached), then beside the
        // vertex, then to it.
        let (back, from) = (self.approach, s.position);
        self.fresh_attempt();
        let path = self.glide(from, back, s.time);
        // The vertex's time starts once it is reached again.
        self.vertex_start = s.time
            + path.duration
            + self.glide(back, beside, 0.0).duration
            + self.glide(beside, vertex.position, 0.0).duration;
        self.phase = Phase::Move {
            path,
            walked: false,
            then: [Some(beside), Some(vertex.position)],
        };
        ControlOutput::force(self.hold_force(&from, s, &self.estimate))
    }

    /// A minimum-jerk glide from `from` to `to` starting at `t`, `move_time` per cell.
    pub(super) fn glide(&self, from: Vector3<f64>, to: Vector3<f64>, t: f64) -> Glide {
        Glide {
            from,
            to,
            start: t,
            duration: self.params.move_time * ((to - from).norm() / self.params.spacing).max(1.0),
        }
    }

    /// A point half a cell beside `vertex`, across the straight way the handle came from
    /// `approach`: along the axis most nearly square to that way, on the side inside the box the
    /// grid spans (with at least two vertices along every axis, one side is), toward the grid's
    /// centre if both are; inside the workspace, m.
    pub(super) fn beside(&self, vertex: &Vector3<f64>, approach: &Vector3<f64>) -> Vector3<f64> {
        let way = vertex - approach;
        let a = (0..3)
            .min_by(|&i, &j| way[i].abs().total_cmp(&way[j].abs()))
            .unwrap_or(0);
        let step = axis(a) * (0.5 * self.params.spacing);
        let lo = self.plan.origin[a];
        let hi = lo + self.plan.dims[a].saturating_sub(1) as f64 * self.params.spacing;
        let inside = |x: f64| x >= lo - 1e-9 && x <= hi + 1e-9;
        let (plus, minus) = (vertex + step, vertex - step);
        let chosen = match (inside(plus[a]), inside(minus[a])) {
            (true, false) => plus,
            (false, true) => minus,
            _ if self.params.centre[a] >= vertex[a] => plus,
            _ => minus,
        };
        let (min, max) = self.params.workspace;
        chosen.zip_zip_map(&min, &max, |x, lo, hi| x.clamp(lo, hi))
    }

    /// Mark the current vertex as not measured (the handle stays `distance` m away; `failure`
    /// None: it did not yield to a push), go back to the last vertex's force and go on. Its
    /// values are filled from its neighbours once the run is over.
    pub(super) fn skip(
        &mut self,
        s: &DeviceState,
        distance: f64,
        failure: Option<CalibrationFailure>,
    ) -> ControlOutput {
        let vertex = self.plan.path[self.vertex];
        self.results[self.vertex] = Some(VertexResult {
            iterations: self.iteration,
            final_error: distance,
            duration: s.time - self.vertex_began,
            failure,
            ..VertexResult::not_reached(vertex)
        });
        self.emit(CalibrationEvent::VertexUnreachable {
            vertex: self.vertex,
            of: self.plan.path.len(),
            at: vertex,
            distance,
            failure,
            retried: self.retried,
            elapsed: self.elapsed(),
        });
        self.normals = self.last_normals;
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        self.next_vertex(s, s.position)
    }

    pub(super) fn next_vertex(&mut self, s: &DeviceState, from: Vector3<f64>) -> ControlOutput {
        self.vertex += 1;
        self.retried = false;
        let of = self.plan.path.len();
        let read = self.results.iter().flatten().filter(|r| r.reached).count();
        // Fewer than half of the vertices measured (or certain to be) is too few to fill in the
        // others.
        let missed = self.vertex - read;
        if self.vertex == of || missed > of - of.div_ceil(2) {
            self.end_time = s.time;
            if read < of.div_ceil(2) {
                // Why the first vertex that was not measured failed, if it was not a stop: it
                // says what to change (a time limit, ε_M, the updates allowed).
                let first = self.results.iter().flatten().find_map(|r| r.failure);
                return self
                    .fail(first.unwrap_or(CalibrationFailure::TooFewVertices { missed, of }));
            }
            self.phase = Phase::Finished;
            self.emit(CalibrationEvent::Finished);
            return ControlOutput::done(Vector3::zeros());
        }
        self.start_move(from, s.time);
        ControlOutput::force(self.hold_force(&from, s, &self.estimate))
    }

    /// Exploration (`calibration.workspace = "explore"`): the explorer's probes, then the grid
    /// replanned on what they found, and its first vertex.
    pub(super) fn explore(&mut self, s: &DeviceState) -> ControlOutput {
        // Without an explorer (never built so) the cube's plan stands and its vertices follow.
        let (force, probed) = match &mut self.explorer {
            Some(explorer) => {
                let force = explorer.tick(s, &self.gains, &self.initial.load);
                let probed = explorer.take_probe().map(|p| (explorer.probes().0 - 1, p));
                (force, probed)
            }
            None => (None, None),
        };
        if let Some((probe, p)) = probed {
            self.emit(CalibrationEvent::Probed {
                probe,
                from: p.from,
                direction: p.direction,
                run: p.run,
                stopped: p.stopped,
            });
        }
        if let Some(force) = force {
            return ControlOutput::force(force);
        }
        if let Some(explorer) = &self.explorer {
            let map = explorer.map();
            if let Err(failure) = self.plan.explore(map, self.params.spacing) {
                return self.fail(failure);
            }
            let (probes, stopped) = explorer.probes();
            let reached = map.reached();
            self.results.clear();
            self.results.resize(self.plan.path.len(), None);
            self.emit(CalibrationEvent::Explored {
                probes,
                stopped,
                reached,
                vertices: self.plan.path.len(),
                extrapolated: self.plan.extrapolated.len(),
                dims: self.plan.dims,
            });
        }
        self.vertex = 0;
        self.start_move(s.position, s.time);
        ControlOutput::force(self.hold_force(&s.position, s, &self.estimate))
    }
}
