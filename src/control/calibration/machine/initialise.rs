//! The initialisation at X_C: the initial field catches the handle, the stick bands along
//! each axis, the moving-mass pulses, and the survey strokes that check the bands.

use super::*;

impl Calibration {
    /// First tick. X_C is where the handle rests (on hardware the user has brought it near the
    /// centre). A handle resting outside the grid's box (say on a stop below it) is first carried
    /// to the grid centre by gliding the field's centre there.
    pub(super) fn start(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        self.start_time = t;
        self.rested_at = s.position;
        let (lo, hi) = self.params.workspace;
        let slack = ((hi - lo) / 2.0 * WORKSPACE_SLACK_SHARE).map(|d| d.max(WORKSPACE_SLACK_MIN));
        let outside = (lo - slack - s.position)
            .sup(&(s.position - hi - slack))
            .max();
        if outside > 0.0 {
            return self.fail(CalibrationFailure::OutsideWorkspace {
                position: s.position,
                lo,
                hi,
                outside,
            });
        }
        let (lo, hi) = (self.plan.origin, self.plan.far_corner());
        let inside = (0..3).all(|a| s.position[a] >= lo[a] && s.position[a] <= hi[a]);
        let to = if inside {
            s.position
        } else {
            self.params.centre
        };
        let cells = (to - s.position).norm() / self.params.spacing;
        let field = Glide {
            from: s.position,
            to,
            start: t,
            duration: if inside {
                0.0
            } else {
                self.params.move_time * cells.max(1.0)
            },
        };
        self.rest_point = to;
        self.phase = Phase::Catch(field);
        self.emit(CalibrationEvent::InitStarted);
        ControlOutput::force(Vector3::zeros())
    }

    /// The initial field centred on `centre`: k_init (X_C − X) − c V̂ plus its gravity term.
    pub(super) fn field_force(&self, centre: &Vector3<f64>, s: &DeviceState) -> Vector3<f64> {
        (centre - s.position) * self.params.k_init
            - s.velocity * (self.params.init_damping * self.field_scale)
            + self.catch_force
    }

    /// The initial field has waited for rest since `since`: after a second without one, halve
    /// its damping (at most three times). Damping strong for a light handle (c T / m near 1)
    /// makes it chatter through the velocity filter's lag, and it never comes to rest.
    pub(super) fn field_back_off(&mut self, s: &DeviceState, since: f64) -> bool {
        let weight = 1.0 / self.params.n_init as f64;
        self.speed_square += (s.velocity.norm_squared() - self.speed_square) * weight;
        if s.time - since > GAIN_BACKOFF_AFTER && self.field_scale > MIN_GAIN_SCALE {
            self.field_scale *= 0.5;
            self.detector.reset();
            self.field_since = s.time;
            return true;
        }
        false
    }

    /// The steady-state test of the initial field: n_init samples within ε_init, or within
    /// `STEADY_STEPS` encoder steps where the encoder is that coarse.
    pub(super) fn init_detector(&self) -> SteadyState {
        let step = self.noise.step();
        let eps = if step.is_finite() {
            self.params.eps_init.max(STEADY_STEPS * step)
        } else {
            self.params.eps_init
        };
        SteadyState::new(self.params.n_init, eps)
    }

    /// A steady state of the initial field, unless the handle chatters about it (small and fast
    /// enough to average out of the windows, but not of the velocity): then the damping is
    /// halved and the wait goes on.
    pub(super) fn field_steady(&mut self, s: &DeviceState) -> Option<Vector3<f64>> {
        let steady = self.detector.push(&s.position)?;
        // An encoder step larger than the velocity filter's noise bound reads as a burst of
        // speed: raise the bound to the step and look again.
        let step = self.noise.step();
        if self.raise_filter_bound(step) {
            self.speed_square = 0.0;
            self.detector = self.init_detector();
            return None;
        }
        let flicker = if step.is_finite() {
            step / FLICKER_TIME
        } else {
            0.0
        };
        let chatter = CHATTER_SPEED.max(flicker);
        if self.speed_square.sqrt() > chatter && self.field_scale > MIN_GAIN_SCALE {
            self.field_scale *= 0.5;
            self.detector.reset();
            self.field_since = s.time;
            return None;
        }
        Some(steady)
    }

    /// The velocity filter's noise bound raised to an encoder `step` larger than it (a step
    /// reads as a burst of speed otherwise): whether it was.
    pub(super) fn raise_filter_bound(&mut self, step: f64) -> bool {
        if step <= self.filter_bound {
            return false;
        }
        let Ok(filter) = Foaw::new(
            self.params.foaw_variant,
            step,
            self.params.max_window,
            self.params.period,
        ) else {
            return false;
        };
        self.filter = filter;
        self.filter_bound = step;
        true
    }

    /// Initialisation, catch (§3.1): the elastic field k_init (X_C − X) plus damping (an
    /// undamped spring never lets a frictionless handle settle) until the handle is at rest.
    /// Unlike the paper, no sag is needed: the load is measured next by pushing. Samples count
    /// only once the glide is over.
    pub(super) fn catch(&mut self, s: &DeviceState, field: Glide) -> ControlOutput {
        let t = s.time;
        if t - field.start > self.params.vertex_timeout + field.duration {
            return self.fail(CalibrationFailure::InitTimeout {
                timeout: self.params.vertex_timeout,
            });
        }
        let mut force = self.field_force(&field.at(t), s);
        // A handle that has not moved yet may be held, or not where the box says: push gently
        // until it follows.
        self.followed |= (s.position - self.rested_at).norm() > SEEN_MOVING;
        let carry_limit = CARRY_SHARE * self.params.max_force;
        if !self.followed {
            force = force.cap_magnitude(carry_limit);
        }
        if field.progress(t) < 1.0 {
            return ControlOutput::force(force);
        }
        self.noise.push(&s.position);
        let since = self.field_since.max(field.start + field.duration);
        self.field_back_off(s, since);
        if self.field_steady(s).is_some() {
            let off = field.to - s.position;
            if !self.followed && off.norm() > SEEN_MOVING {
                return self.held(t, off.iamax(), carry_limit);
            }
            self.initial.noise = self.noise.sigma();
            // A step adopted from the bands' slips (below) stands if the handle is caught again.
            self.initial.step = self.noise.step().max(self.initial.step);
            self.set_slip();
            if self.params.prior.is_some() {
                return self.initialised_from(self.field_force(&field.to, s), s);
            }
            self.phase = self.init_band_along(0, t);
        }
        ControlOutput::force(force)
    }

    /// The initialisation from an earlier calibration's ([`super::super::Prior`]), the handle
    /// caught at X_C by the force `caught`: the load is the prior's, moved to within the prior
    /// friction of `caught` (where the handle came to rest, the field held the load to within
    /// the friction); then the first vertex.
    pub(super) fn initialised_from(
        &mut self,
        caught: Vector3<f64>,
        s: &DeviceState,
    ) -> ControlOutput {
        let Some(prior) = &self.params.prior else {
            return ControlOutput::force(caught);
        };
        // The saved model's force at X_C where it gives one (the record's load is a band's
        // middle, a few tens of millinewtons off on a linkage).
        let load = prior.expected_at(&self.rest_point).unwrap_or(prior.load);
        self.initial.load = Vector3::from_fn(|a, _| {
            load[a].clamp(caught[a] - prior.friction[a], caught[a] + prior.friction[a])
        });
        self.initial.friction = prior.friction;
        self.initial.inertia = prior.inertia;
        // The encoder's step the calibration saw (a handle caught at once shows none).
        self.initial.step = self.initial.step.max(prior.step);
        self.set_slip();
        self.raise_filter_bound(self.initial.step);
        self.initialised();
        self.report_initialisation();
        self.catch_force = self.initial.load;
        self.vertex = 0;
        self.start_move(self.rest_point, s.time);
        ControlOutput::force(caught)
    }

    /// Initialisation, load and friction: the stick band along each axis under the initial
    /// field. Its middle is the load at X_C, its half-width the friction. A handle that does
    /// not move under the ramp's whole push is held (by a hand, say): catch it again and
    /// measure again, until the initialisation's time is up.
    pub(super) fn init_band(&mut self, s: &DeviceState, mut probe: BandProbe) -> ControlOutput {
        let t = s.time;
        let a = probe.index();
        let force = self.field_force(&self.rest_point, s) + axis(a) * probe.offset(t);
        match probe.observe(s, &self.smoothed, &force) {
            Step::Running => self.phase = Phase::InitBand(probe),
            // A handle that rested on one encoder reading, without noise, showed no step while
            // it was caught: the slip threshold assumed a fine encoder, and a reading that flips
            // by one step without a slip (a handle resting at a step's edge) passed for one.
            // The band's slips have moved the handle since: with the step they showed, measure
            // the bands again.
            Step::Done(_) if self.initial.step == 0.0 && self.moving.step() > 0.0 => {
                self.initial.step = self.moving.step();
                self.set_slip();
                self.phase = self.init_band_along(0, t);
            }
            Step::Done(band) => {
                self.initial.load[a] = band.middle();
                self.initial.friction[a] = band.half_width();
                self.phase = if a < 2 {
                    self.init_band_along(a + 1, t)
                } else {
                    self.time_moving_mass(t)
                };
            }
            Step::Blocked { .. } => return self.held(t, a, self.push_limit()),
        }
        ControlOutput::force(force)
    }

    /// A slip is a move beyond the noise and beyond an encoder step (a reading flickering
    /// between two steps is no move); a reading within half a step and two standard deviations
    /// of where the handle stuck has not moved yet.
    pub(super) fn set_slip(&mut self) {
        self.slip = (MIN_SLIP + 3.0 * self.initial.noise).max(SLIP_STEPS * self.initial.step);
        self.still = 0.5 * self.initial.step + 2.0 * self.initial.noise;
    }

    /// The band along axis `a` at X_C, from `t`.
    pub(super) fn init_band_along(&self, a: usize, t: f64) -> Phase {
        Phase::InitBand(BandProbe::new(
            a,
            axis(a),
            self.init_ramp(),
            self.slip,
            self.still,
            t,
        ))
    }

    /// With the load and friction measured: back to X_C with the load as the field's gravity
    /// term, then the pulses that time the moving mass, from `t`.
    pub(super) fn time_moving_mass(&mut self, t: f64) -> Phase {
        self.catch_force = self.initial.load;
        self.detector = self.init_detector();
        Phase::Recentre {
            axis: 0,
            excess: self.pulse_excess(0),
            since: t,
        }
    }

    /// The ramp of a band measurement at X_C, where the band is not known yet: from the rate
    /// that moves a frictionless handle by a slip in `DETECT_TIME` against the initial field,
    /// growing at once.
    pub(super) fn init_ramp(&self) -> Ramp {
        Ramp {
            rate: self.init_ramp_rate(),
            steady: INIT_RAMP_STEADY,
            growth: INIT_RAMP_GROWTH,
            limit: self.push_limit(),
        }
    }

    pub(super) fn init_ramp_rate(&self) -> f64 {
        (self.params.k_init * self.slip / DETECT_TIME).max(INIT_RAMP_RATE)
    }

    /// The half-width a frictionless handle of moving mass `m` seems to have at X_C: the
    /// initial field's force over a slip, plus what the ramp adds while m accelerates over a
    /// slip (x = r t³ / 6m).
    pub(super) fn apparent_band(&self, m: f64) -> f64 {
        let rate = self.init_ramp_rate();
        self.params.k_init * self.slip + rate.powf(2.0 / 3.0) * (6.0 * m * self.slip).cbrt()
    }

    /// The handle did not move under `push` N along `axis`: wait for it to be let go, catching
    /// it again, or give up once the initialisation's time is up.
    pub(super) fn held(&mut self, t: f64, axis: usize, push: f64) -> ControlOutput {
        if t - self.start_time > self.params.vertex_timeout {
            return self.fail(CalibrationFailure::Held {
                axis: ['x', 'y', 'z'][axis],
                push_n: push,
            });
        }
        self.catch_force = Vector3::zeros();
        self.detector = self.init_detector();
        self.phase = Phase::Catch(Glide {
            from: self.rest_point,
            to: self.rest_point,
            start: t,
            duration: 0.0,
        });
        ControlOutput::force(Vector3::zeros())
    }

    /// The least push beyond the band that times the moving mass well: the friction, a tenth of
    /// the load (the load changes over the pulse wherever the apparent mass varies), or
    /// `PULSE_MIN_EXCESS`.
    pub(super) fn pulse_excess(&self, a: usize) -> f64 {
        self.initial.friction[a]
            .max(PULSE_LOAD_SHARE * self.initial.load.norm())
            .max(PULSE_MIN_EXCESS)
    }

    /// Initialisation: the initial field, with the measured load as its gravity term, brings the
    /// handle back to X_C and lets it settle; then the next pulse, or the first vertex.
    pub(super) fn recentre(
        &mut self,
        s: &DeviceState,
        a: usize,
        excess: f64,
        since: f64,
    ) -> ControlOutput {
        let t = s.time;
        if t - since > self.params.vertex_timeout {
            return self.fail(CalibrationFailure::InitTimeout {
                timeout: self.params.vertex_timeout,
            });
        }
        let force = self.field_force(&self.rest_point, s);
        self.noise.push(&s.position);
        self.field_back_off(s, since.max(self.field_since));
        let Some(steady) = self.field_steady(s) else {
            return ControlOutput::force(force);
        };
        self.initial.noise = self.initial.noise.min(self.noise.sigma());
        if a == 3 {
            self.initialised();
            self.phase = Phase::InitStrokes(Strokes::along_axes(Stroke::SURVEY, steady, t));
            return ControlOutput::force(force);
        }
        self.phase = Phase::Pulse(Pulse::new(
            a,
            excess,
            PULSE_DISTANCE,
            PULSE_TIMEOUT,
            &steady,
            t,
        ));
        ControlOutput::force(self.pulse_force(a, excess))
    }

    /// The load plus the friction plus `excess` along +axis `a`, and no spring.
    pub(super) fn pulse_force(&self, a: usize, excess: f64) -> Vector3<f64> {
        self.initial.load + axis(a) * (self.initial.friction[a] + excess)
    }

    /// Initialisation, moving mass: the pulse along one axis, then back to X_C. A pulse that did
    /// not move the handle in time is repeated twice as strong, up to the push limit.
    pub(super) fn pulse(&mut self, s: &DeviceState, mut pulse: Pulse) -> ControlOutput {
        let t = s.time;
        let a = pulse.axis;
        let (next_axis, excess) = match pulse.observe(s) {
            Step::Running => {
                self.phase = Phase::Pulse(pulse);
                return ControlOutput::force(self.pulse_force(a, pulse.excess));
            }
            Step::Done(mass) => {
                self.initial.inertia[a] = mass;
                self.timed_excess[a] = pulse.excess;
                (a + 1, self.pulse_excess((a + 1).min(2)))
            }
            Step::Blocked { .. } => {
                let excess = 2.0 * pulse.excess;
                if excess > self.push_limit() {
                    return self.held(t, a, self.initial.friction[a] + pulse.excess);
                }
                (a, excess)
            }
        };
        self.detector = self.init_detector();
        self.phase = Phase::Recentre {
            axis: next_axis,
            excess,
            since: t,
        };
        ControlOutput::force(self.field_force(&self.rest_point, s))
    }

    /// The hold's gains and the friction's kind along each axis from what the initialisation
    /// measured.
    pub(super) fn initialised(&mut self) {
        let (inertia, friction, load) = (
            self.initial.inertia,
            self.initial.friction,
            self.initial.load,
        );
        self.gains = AxisGains::from_measurement(
            &self.params.gains,
            &inertia,
            &friction,
            FRICTION_OFFSET.max(FRICTION_OFFSET_STEPS * self.initial.step),
            MAX_OMEGA_PERIODS / self.params.period,
        );
        self.initial.stiffness = self.gains.stiffness;
        self.settle_time = SETTLE_RADIANS / self.gains.slowest_omega(&inertia);
        self.friction_kind = [0, 1, 2].map(|a| {
            let apparent = self.apparent_band(inertia[a]);
            if friction[a] > DOMINANT_BANDS * apparent + DOMINANT_FLOOR {
                Friction::Dominant
            } else if friction[a] > apparent {
                Friction::Slight
            } else {
                Friction::None
            }
        });
        self.share_friction_kind();
        self.learn_normals = false;
        self.estimate = load;
        self.last_good = load;
    }

    /// The initialisation is over (after the survey strokes): what it measured.
    pub(super) fn report_initialisation(&mut self) {
        let InitialMeasurement {
            load,
            friction,
            inertia,
            ..
        } = self.initial;
        self.emit(CalibrationEvent::InitDone {
            gravity_direction: if load.norm() > 0.0 {
                load.normalize()
            } else {
                Vector3::z()
            },
            initial_mass: load.norm() / self.params.g,
            friction,
            inertia,
        });
    }

    /// One mechanism, one kind of friction: where it dominates along one axis, a hold at rest
    /// without velocity feedback along the others too (they share its joints).
    pub(super) fn share_friction_kind(&mut self) {
        if self.friction_kind.contains(&Friction::Dominant) {
            for kind in &mut self.friction_kind {
                if *kind == Friction::Slight {
                    *kind = Friction::Dominant;
                }
            }
        }
    }

    /// Whether the bands at X_C misread some frictional axis (one whose survey strokes slid
    /// against more than `STROKE_FRICTION`, which a frictionless handle's passes stay under):
    /// its friction under `MISREAD_SHARE` of the strokes', or its middle further from the
    /// strokes' force than `STROKE_REPEAT` (PHANToM unit 2, seed 1, 0.02 N: 47 mN off along y,
    /// and a 925 g moving mass timed from it).
    pub(super) fn bands_misread(&self, stroked: &Stroked) -> bool {
        (0..3).any(|a| {
            let sliding = stroked.friction[a].abs();
            let narrow = self.initial.friction[a] < MISREAD_SHARE * sliding;
            let off = (stroked.force[a] - self.initial.load[a]).abs() > STROKE_REPEAT;
            sliding > STROKE_FRICTION && (narrow || off)
        })
    }

    /// The share of its excess that the pulse along `a` pushed the sliding handle with: it
    /// applied the bands' load and friction plus the excess, and what the handle accelerated
    /// under is what that leaves over the load and sliding friction the survey strokes found.
    /// The bands' edges are read at a slip, late (sound bands read 105–130 % of the sliding
    /// friction on the simulated PHANToM): a pulse pushed harder than meant, and the moving
    /// mass read light. PHANToM unit 2, seed 1 at 0.04 N: the band along z read 0.052 N of
    /// friction where the handle slides against 0.087, its load 8 mN off; the pulse pushed by
    /// 0.18 of its 0.052 N excess and timed 0.353 kg where the arm's is about 0.065. (An axis
    /// never pulsed has no excess: its share is not finite, and `PULSE_SHARES` leaves it.)
    fn pulse_share(&self, a: usize, stroked: &Stroked) -> f64 {
        let overstated = self.initial.load[a] + self.initial.friction[a]
            - stroked.force[a]
            - stroked.friction[a].abs();
        1.0 + overstated / self.timed_excess[a]
    }

    /// The moving mass along each axis as the pulse pushed it (see [`Self::pulse_share`]; a
    /// share beyond `PULSE_SHARES` is left alone). It is what the calibration reports and
    /// saves (the watch of docs/calibration.md §2.3 reads a released handle with it, a later
    /// check's holds build their gains on it); this calibration's hold keeps the gains built on
    /// the pulses' own reading (rebuilt here, they changed how three of the test suite's
    /// calibrations went).
    fn correct_moving_mass(&mut self, stroked: &Stroked) {
        for a in 0..3 {
            let share = self.pulse_share(a, stroked);
            if PULSE_SHARES.contains(&share) {
                self.initial.inertia[a] *= share;
            }
        }
    }

    /// The strokes at X_C ([`Phase::InitStrokes`]): an axis the bands took for frictionless
    /// whose passes differ by more than `STROKE_FRICTION` has friction after all (or viscous
    /// damping well beyond 1 N·s/m, which strokes measure through as well), and is measured as
    /// such at every vertex. Then the first vertex.
    pub(super) fn init_strokes(&mut self, s: &DeviceState, mut strokes: Strokes) -> ControlOutput {
        let force = self.stroke_force(&strokes, s);
        match strokes.observe(s, &force) {
            Step::Running => {
                self.phase = Phase::InitStrokes(strokes);
                return ControlOutput::force(force);
            }
            // A band far narrower than the friction the strokes slide against was misread (the
            // handle shook at the start of a crossing, and a slip was taken early), and so was
            // its middle. The moving mass was timed with that load and friction, and the gains
            // built on both: time it again with the strokes' load and sliding friction, then
            // survey again.
            Step::Done(stroked)
                if self.init_remeasured < INIT_REMEASURES && self.bands_misread(&stroked) =>
            {
                self.init_remeasured += 1;
                self.initial.load = stroked.force;
                self.initial.friction = stroked.friction.abs();
                self.phase = self.time_moving_mass(s.time);
                return ControlOutput::force(self.field_force(&self.rest_point, s));
            }
            Step::Done(stroked) => {
                self.correct_moving_mass(&stroked);
                self.initial.sliding_friction = Some(stroked.friction.abs());
                for a in 0..3 {
                    if self.friction_kind[a] == Friction::None
                        && stroked.friction[a].abs() > STROKE_FRICTION
                    {
                        self.friction_kind[a] = Friction::Slight;
                    }
                }
                self.share_friction_kind();
            }
            // The hold did not carry the handle through a window: the bands misread its load
            // so far that the hold keeps it off the window (a stop within 2 mm of the user's
            // centre is unlikely). Measure the bands again.
            Step::Blocked { .. } if self.init_remeasured < INIT_REMEASURES => {
                self.init_remeasured += 1;
                self.phase = self.init_band_along(0, s.time);
                return ControlOutput::force(self.field_force(&self.rest_point, s));
            }
            // A stop within a stroke of X_C: the bands' classes stand.
            Step::Blocked { .. } => {}
        }
        self.report_initialisation();
        if let Some(explorer) = &mut self.explorer {
            explorer.begin(strokes.centre(), s.time);
            self.phase = Phase::Explore;
            return ControlOutput::force(self.stroke_force(&strokes, s));
        }
        self.vertex = 0;
        self.start_move(strokes.centre(), s.time);
        ControlOutput::force(force)
    }
}
