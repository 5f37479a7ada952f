//! The evidence diagnosis reads: every (row, string) residual of the
//! current fit with what it depends on ([`Row`]), and the model's span the
//! candidates are tested off ([`Evidence`]).
//!
//! ## Rows made when read
//! A tracked observation gives a row per string: 800,000 rows for a
//! 100,000-row session. Neither the rows nor the model's span (an
//! orthonormal basis of the data Jacobian's columns, a value per row and
//! parameter) are held: each pass over the rows makes them again from the
//! observations, the fit and the data Jacobian ([`DataJacobian`]), and what
//! is held is a few numbers per row (the weights and the residuals). Held,
//! rows, basis and the candidates' columns took 1.6 GB for a 15 MB session.
//! The sums over the rows are taken in the order and with the rounding of
//! the dense matrix products they stand for (`span`), so every figure is
//! the same as theirs.

mod span;

use std::sync::OnceLock;

#[cfg(test)]
use nalgebra::DMatrix;
use nalgebra::DVector;
use spidar_core::model::{Frame, StringInputs, StringLayout};
use spidar_core::string_law::{payout_f64, total_tension_n, EffectContext, StringHome};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::model::identify::{device_position, inputs_at, DataJacobian, Identification, Structure};

pub(super) use span::{Columns, OffSpan};
use span::{Span, SquaresSum};

/// What one (row, string) residual depends on.
#[derive(Clone, Copy, Debug)]
pub(super) struct Row {
    /// Index into the observations.
    pub(super) obs: usize,
    pub(super) string: usize,
    /// Weight of the robust fit (0 for rejected residuals).
    pub(super) weight: f64,
    pub(super) ctx: EffectContext,
    /// Geometric length from the tracker, mm.
    pub(super) length: f64,
    /// String speed `d payout / dt` since the previous row, mm/s.
    pub(super) speed: f64,
    /// Device-frame position from the tracker, mm.
    pub(super) position: [f64; 3],
    /// How the string's length reads a move of the tracked body's origin
    /// from the meeting point (body frame, per mm of each axis), when the
    /// tracker gives the body's orientation: a marker offset's columns.
    pub(super) marker_column: Option<[f64; 3]>,
    /// `d residual / d room_scale` (frame-wide geometry regressor).
    pub(super) scale_gradient: f64,
}

/// A column's value on one row (a candidate effect's regressor).
pub(super) type RowColumn = Box<dyn Fn(&Row) -> f64 + Send + Sync>;

/// Everything diagnosis needs about the current fit.
pub(super) struct Evidence<'a> {
    /// Which channels carry a string (rows of the others have weight 0).
    pub(super) layout: StringLayout,
    source: Source<'a>,
    /// Weighted residual with the model's directions projected out, row by
    /// row.
    pub(super) residual: DVector<f64>,
    /// Residual variance per unit weight, mm^2.
    pub(super) sigma2: f64,
    /// Whether the rows carry the strings' count rates (a stream:
    /// `data::observe::speed_observation`), so that a latency can be told.
    pub(super) speed_observed: bool,
    /// Weighted residual sum of squares, mm^2.
    pub(super) rss: f64,
}

/// Where the rows and the model's span come from.
// The large variant is the tests' own; one `Source` lives per evidence.
#[cfg_attr(test, allow(clippy::large_enum_variant))]
enum Source<'a> {
    /// A fit's: made from its observations when read.
    Fit(FitRows<'a>),
    /// Given whole, with their residuals (unweighted) and the span's
    /// orthonormal basis (a row per row): tests' evidence of their own
    /// making.
    #[cfg(test)]
    Given {
        rows: Vec<Row>,
        residuals: Vec<f64>,
        basis: DMatrix<f64>,
    },
}

/// A fit's rows: row `u * STRINGS + i` is string `i` of the `u`-th
/// observation with a tracker position.
struct FitRows<'a> {
    id: &'a Identification,
    observations: &'a [Observation],
    /// Index into `observations` of each one with a tracker position.
    used: Vec<usize>,
    jacobian: DataJacobian<'a>,
    span: Span,
    /// Each string's home terms in the model's frame (once, not per row).
    homes: [Option<StringHome>; STRINGS],
    /// Every observation's basis rows, worked out at the first pass that
    /// reads them and kept for the diagnosis's other passes (a test and
    /// its rivals' read them four to six times), when the diagnosis reads
    /// at most [`KEPT_OBSERVATIONS`]; `None` inside: recomputed at every
    /// pass.
    basis_kept: OnceLock<Option<Vec<f64>>>,
    /// Every observation's rows ([`Row`], a string's after another's),
    /// kept as `basis_kept` is.
    rows_kept: OnceLock<Option<Vec<Option<Row>>>>,
}

/// What a row's strings share: its observation as the fit reads it.
struct Observed<'o> {
    k: usize,
    o: &'o Observation,
    previous: Option<&'o Observation>,
    p: [f64; 3],
    inputs: StringInputs,
    /// The active strings' total tension (N), once per row.
    total_tension_n: f64,
    body_in_device: Option<[[f64; 3]; 3]>,
}

/// A column whose part off the model's span (or off the other columns')
/// is under this share of its norm lies (almost) in it: the model already
/// absorbs it and the data cannot show it.
pub(super) const MIN_OUTSIDE_SPAN: f64 = 1e-2;

pub(super) fn pulley_turn_angle(theta: f64) -> f64 {
    theta.rem_euclid(2.0 * std::f64::consts::PI)
}

impl<'a> Evidence<'a> {
    pub(super) fn gather(
        id: &'a Identification,
        observations: &'a [Observation],
        nominal: &'a Frame<f64>,
        structure: &'a Structure,
    ) -> Option<Evidence<'a>> {
        let jacobian = DataJacobian::new(id, observations, nominal, structure)?;
        let used: Vec<usize> = observations
            .iter()
            .enumerate()
            .filter(|(_, o)| o.tracker.is_some())
            .map(|(k, _)| k)
            .collect();
        // Orthonormal basis of the column space from the eigenvectors of J^T J
        // (the data Jacobian alone is rank deficient: the gauge is fixed by priors).
        let gram = jacobian.gram()?;
        let eig = gram.symmetric_eigen();
        let max = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let keep: Vec<usize> = (0..eig.eigenvalues.len())
            .filter(|&j| eig.eigenvalues[j] > 1e-10 * max)
            .collect();
        let span = Span::new(&jacobian, &eig, &keep);
        let effective = jacobian
            .weights()
            .iter()
            .flatten()
            .filter(|&&w| w > 0.0)
            .count();
        let speed_observed = crate::data::observe::observes_speed(observations);
        let mut ev = Evidence {
            layout: nominal.layout,
            speed_observed,
            source: Source::Fit(FitRows {
                id,
                observations,
                used,
                jacobian,
                span,
                homes: StringHome::of_every_string(&id.frame),
                basis_kept: OnceLock::new(),
                rows_kept: OnceLock::new(),
            }),
            residual: DVector::zeros(0),
            sigma2: 0.0,
            rss: 0.0,
        };
        ev.project_residual(keep.len());
        let dof = (effective as f64 - keep.len() as f64).max(1.0);
        ev.sigma2 = ev.rss / dof;
        Some(ev)
    }

    /// The context of a test's row at `time_s`: a string 1 m long at home,
    /// still, pulling 1 N of the 8 its device's strings pull.
    #[cfg(test)]
    pub(super) fn still_context(time_s: f64) -> EffectContext {
        EffectContext {
            theta: 0.0,
            payout_mm: 0.0,
            home_length_mm: 1000.0,
            tension_n: 1.0,
            total_tension_n: 8.0,
            direction: 0,
            time_s,
            cos2_inclination: 1.0,
            home_cos2_inclination: 1.0,
            guide_elevation_rad: 0.0,
            home_guide_elevation_rad: 0.0,
            payout_rate_mm_s: 0.0,
        }
    }

    /// Evidence of `rows` (their `weight` as the fit's), their
    /// `residuals` (unweighted), the model's span given by its orthonormal
    /// `basis` (a row per row), and the residual variance `sigma2`.
    #[cfg(test)]
    pub(super) fn of_rows(
        rows: Vec<Row>,
        residuals: Vec<f64>,
        basis: DMatrix<f64>,
        sigma2: f64,
    ) -> Evidence<'static> {
        let dims = basis.ncols();
        let mut ev = Evidence {
            layout: StringLayout::ALL,
            speed_observed: false,
            source: Source::Given {
                rows,
                residuals,
                basis,
            },
            residual: DVector::zeros(0),
            sigma2,
            rss: 0.0,
        };
        ev.project_residual(dims);
        ev
    }

    /// `residual` and `rss` from the weighted residual `r`: `r - B (B^T
    /// r)` (`B` the span's basis, of `dims` directions) and its sum of
    /// squares.
    fn project_residual(&mut self, dims: usize) {
        let rows = self.rows();
        let mut coef = vec![0.0; dims];
        self.visit_rows(None, Visit::Basis, |k, _, b| {
            let w = self.weighted(k);
            if w != 0.0 {
                for (c, &bc) in coef.iter_mut().zip(b) {
                    *c += bc * w;
                }
            }
        });
        let mut residual = DVector::zeros(rows);
        let mut squares = SquaresSum::new(rows);
        self.visit_rows(None, Visit::Basis, |k, _, b| {
            let r = self.weighted(k) - span::dot_in_turn(b, &coef);
            residual[k] = r;
            squares.add(k, r);
        });
        self.residual = residual;
        self.rss = squares.total();
    }

    /// Number of rows.
    pub(super) fn rows(&self) -> usize {
        match &self.source {
            Source::Fit(fit) => fit.jacobian.rows(),
            #[cfg(test)]
            Source::Given { rows, .. } => rows.len(),
        }
    }

    /// Row `k`'s residual weighted by the square root of its robust
    /// weight.
    fn weighted(&self, k: usize) -> f64 {
        match &self.source {
            Source::Fit(fit) => fit.jacobian.residuals()[k],
            #[cfg(test)]
            Source::Given {
                rows, residuals, ..
            } => residuals[k] * rows[k].weight.sqrt(),
        }
    }

    /// Row `k`'s string.
    pub(super) fn string_of(&self, k: usize) -> usize {
        match &self.source {
            Source::Fit(_) => k % STRINGS,
            #[cfg(test)]
            Source::Given { rows, .. } => rows[k].string,
        }
    }

    /// Row `k`'s robust weight.
    pub(super) fn weight(&self, k: usize) -> f64 {
        match &self.source {
            Source::Fit(fit) => fit.jacobian.weights()[k / STRINGS][k % STRINGS],
            #[cfg(test)]
            Source::Given { rows, .. } => rows[k].weight,
        }
    }

    /// Row `k`'s time since initialization (s), as its context reads it.
    pub(super) fn time_of(&self, k: usize) -> f64 {
        match &self.source {
            Source::Fit(fit) => {
                f64::from(fit.observations[fit.used[k / STRINGS]].inputs.time_ms) / 1000.0
            }
            #[cfg(test)]
            Source::Given { rows, .. } => rows[k].ctx.time_s,
        }
    }

    /// Row `k`'s residual (geometric minus model, mm), unweighted.
    pub(super) fn residual_of(&self, k: usize) -> f64 {
        match &self.source {
            Source::Fit(_) => {
                let w = self.weight(k);
                if w > 0.0 {
                    self.weighted(k) / w.sqrt()
                } else {
                    0.0
                }
            }
            #[cfg(test)]
            Source::Given { residuals, .. } => residuals[k],
        }
    }

    /// How many rows string `string` has.
    pub(super) fn rows_of_string(&self, string: usize) -> usize {
        (0..self.rows())
            .filter(|&k| self.string_of(k) == string)
            .count()
    }

    /// Whether the tracker gave the body's orientation on every row.
    pub(super) fn every_row_oriented(&self) -> bool {
        match &self.source {
            Source::Fit(fit) => fit
                .used
                .iter()
                .all(|&k| fit.observations[k].tracker_rotation.is_some()),
            #[cfg(test)]
            Source::Given { rows, .. } => rows.iter().all(|r| r.marker_column.is_some()),
        }
    }

    /// The rows of weight above 0 (of string `string`, or of every
    /// string) in time order: (time, row). Rows of one time keep their
    /// order, so that each string's rows keep theirs among every string's.
    pub(super) fn rows_in_time(&self, string: Option<usize>) -> Vec<(f64, usize)> {
        let mut rows: Vec<(f64, usize)> = (0..self.rows())
            .filter(|&k| string.is_none_or(|s| self.string_of(k) == s) && self.weight(k) > 0.0)
            .map(|k| (self.time_of(k), k))
            .collect();
        rows.sort_by(|a, b| a.0.total_cmp(&b.0));
        rows
    }

    /// Calls `visit(k, row)` on every row of `string` (of every string with
    /// `None`), in order.
    pub(super) fn for_each_row(&self, string: Option<usize>, mut visit: impl FnMut(usize, &Row)) {
        self.visit_rows(string, Visit::Rows, |k, row, _| {
            if let Some(row) = row {
                visit(k, row);
            }
        });
    }

    /// Calls `visit(k, row, basis)` on every row in order, with the row of
    /// the span's orthonormal basis.
    pub(super) fn for_each_row_with_basis(&self, mut visit: impl FnMut(usize, &Row, &[f64])) {
        self.visit_rows(None, Visit::Both, |k, row, b| {
            if let Some(row) = row {
                visit(k, row, b);
            }
        });
    }

    /// Calls `visit(k, time, basis)` on the rows of weight above 0 in the
    /// reverse of [`rows_in_time`](Self::rows_in_time)'s order (every
    /// string's), with each one's row of the span's orthonormal basis: a
    /// fit's observations in time order (held, a row's place in it would
    /// take eight times the room), each observation's strings last first.
    pub(super) fn for_basis_rows_latest_first(&self, mut visit: impl FnMut(usize, f64, &[f64])) {
        match &self.source {
            Source::Fit(fit) => {
                let mut order: Vec<(f64, usize)> = (0..fit.used.len())
                    .map(|u| (self.time_of(u * STRINGS), u))
                    .collect();
                order.sort_by(|a, b| a.0.total_cmp(&b.0));
                let dims = fit.span.dims();
                order.reverse();
                let mut basis = Vec::new();
                for chunk in order.chunks(BASIS_CHUNK) {
                    let us: Vec<usize> = chunk.iter().map(|&(_, u)| u).collect();
                    fit.basis_rows_of(&us, &mut basis);
                    for (j, &(time, u)) in chunk.iter().enumerate() {
                        for i in (0..STRINGS).rev() {
                            let k = u * STRINGS + i;
                            if self.weight(k) > 0.0 {
                                let at = (j * STRINGS + i) * dims;
                                visit(k, time, &basis[at..at + dims]);
                            }
                        }
                    }
                }
            }
            #[cfg(test)]
            Source::Given { basis, .. } => {
                for (time, k) in self.rows_in_time(None).into_iter().rev() {
                    let b: Vec<f64> = basis.row(k).iter().copied().collect();
                    visit(k, time, &b);
                }
            }
        }
    }

    /// Calls `visit(k, row, basis)` on the rows of `string` (or every row)
    /// in order: with the row when `what` asks for it (`None` for a row
    /// without, which a fit's rows never are), with its row of the span's
    /// basis when `what` asks for it (else empty).
    fn visit_rows(
        &self,
        string: Option<usize>,
        what: Visit,
        mut visit: impl FnMut(usize, Option<&Row>, &[f64]),
    ) {
        match &self.source {
            Source::Fit(fit) => fit.visit_rows(string, what, &mut visit),
            #[cfg(test)]
            Source::Given { rows, basis, .. } => {
                for (k, row) in rows.iter().enumerate() {
                    if string.is_none_or(|s| row.string == s) {
                        let b: Vec<f64> = match what {
                            Visit::Rows => Vec::new(),
                            Visit::Basis | Visit::Both => basis.row(k).iter().copied().collect(),
                        };
                        visit(k, Some(row), &b);
                    }
                }
            }
        }
    }
}

/// Observations whose basis rows are worked out at once (in parallel, then
/// visited in order): a few hundred kB of rows at a time.
const BASIS_CHUNK: usize = 512;

/// Most observations whose basis rows and rows ([`Row`]) a diagnosis keeps
/// between its passes: the loop's default bound
/// on the rows it reads (`CalibrateConfig::max_loop_rows`), about 5 kB an
/// observation, 20-30 MB in all. A loop that reads more (every row of a
/// long session, when asked) works them out at each pass: kept, they would
/// grow with the session at twenty times its file's size.
pub(super) const KEPT_OBSERVATIONS: usize = 4000;

/// Fewest observations per task of [`FitRows::basis_rows_of`]: each task
/// sets up its own pass over the Jacobian.
const BASIS_MIN_TASK: usize = 64;

/// What a pass over the rows makes.
#[derive(Clone, Copy, PartialEq)]
enum Visit {
    Rows,
    Basis,
    Both,
}

impl FitRows<'_> {
    fn visit_rows(
        &self,
        string: Option<usize>,
        what: Visit,
        visit: &mut impl FnMut(usize, Option<&Row>, &[f64]),
    ) {
        let dims = self.span.dims();
        let width = STRINGS * dims;
        let observations = self.used.len();
        // What is kept is read where it is, a chunk's slice of it.
        let kept_basis = (what != Visit::Rows).then(|| self.basis_kept()).flatten();
        let kept_rows = (what != Visit::Basis).then(|| self.rows_kept()).flatten();
        let (mut basis_made, mut rows_made) = (Vec::new(), Vec::new());
        for start in (0..observations).step_by(BASIS_CHUNK) {
            let chunk = start..(start + BASIS_CHUNK).min(observations);
            let us = || chunk.clone().collect::<Vec<usize>>();
            let basis: &[f64] = match (what, kept_basis) {
                (Visit::Rows, _) => &[],
                (_, Some(kept)) => &kept[chunk.start * width..chunk.end * width],
                (_, None) => {
                    self.work_out_basis_rows(&us(), &mut basis_made);
                    &basis_made
                }
            };
            let rows: &[Option<Row>] = match (what, kept_rows) {
                (Visit::Basis, _) => &[],
                (_, Some(kept)) => &kept[chunk.start * STRINGS..chunk.end * STRINGS],
                (_, None) => {
                    self.work_out_rows(&us(), &mut rows_made);
                    &rows_made
                }
            };
            for (j, u) in chunk.enumerate() {
                for i in 0..STRINGS {
                    if string.is_some_and(|s| s != i) {
                        continue;
                    }
                    let row = rows.get(j * STRINGS + i).and_then(Option::as_ref);
                    let b = match what {
                        Visit::Rows => &[][..],
                        Visit::Basis | Visit::Both => {
                            let at = (j * STRINGS + i) * dims;
                            &basis[at..at + dims]
                        }
                    };
                    visit(u * STRINGS + i, row, b);
                }
            }
        }
    }

    /// Every observation's rows, once worked out, when they are few enough
    /// to keep ([`KEPT_OBSERVATIONS`]).
    fn rows_kept(&self) -> Option<&[Option<Row>]> {
        self.kept(&self.rows_kept, Self::work_out_rows)
    }

    /// What `work_out` makes of every observation, kept in `cell` the first
    /// time, when the observations are few enough to keep
    /// ([`KEPT_OBSERVATIONS`]).
    fn kept<'s, T>(
        &'s self,
        cell: &'s OnceLock<Option<Vec<T>>>,
        work_out: impl FnOnce(&Self, &[usize], &mut Vec<T>),
    ) -> Option<&'s [T]> {
        cell.get_or_init(|| {
            (self.used.len() <= KEPT_OBSERVATIONS).then(|| {
                let all: Vec<usize> = (0..self.used.len()).collect();
                let mut kept = Vec::new();
                work_out(self, &all, &mut kept);
                kept
            })
        })
        .as_deref()
    }

    /// The rows ([`row`](Self::row)) of the tracked observations `us` into
    /// `rows`, one observation's strings after another's, worked out on
    /// every core (each row is its own, so they are those of one after the
    /// other).
    fn work_out_rows(&self, us: &[usize], rows: &mut Vec<Option<Row>>) {
        use rayon::prelude::*;
        rows.clear();
        rows.par_extend(
            us.par_iter()
                .with_min_len(BASIS_MIN_TASK)
                .flat_map_iter(|&u| {
                    let at = self.observed(u);
                    (0..STRINGS).map(move |i| self.row(u, &at, i))
                }),
        );
    }

    /// The basis rows ([`basis_rows`](Self::basis_rows)) of the tracked
    /// observations `us` into `basis`, one observation's after another's,
    /// worked out on every core: each row is its own, so the values are
    /// those of one pass after the other.
    fn basis_rows_of(&self, us: &[usize], basis: &mut Vec<f64>) {
        let width = STRINGS * self.span.dims();
        basis.clear();
        if let Some(kept) = self.basis_kept() {
            for &u in us {
                basis.extend_from_slice(&kept[u * width..(u + 1) * width]);
            }
            return;
        }
        self.work_out_basis_rows(us, basis);
    }

    /// Every observation's basis rows, once worked out, when they are few
    /// enough to keep ([`KEPT_OBSERVATIONS`]).
    fn basis_kept(&self) -> Option<&[f64]> {
        self.kept(&self.basis_kept, Self::work_out_basis_rows)
    }

    /// [`basis_rows_of`](Self::basis_rows_of) from the Jacobian.
    fn work_out_basis_rows(&self, us: &[usize], basis: &mut Vec<f64>) {
        use rayon::prelude::*;
        let width = STRINGS * self.span.dims();
        basis.clear();
        basis.resize(us.len() * width, 0.0);
        if width == 0 {
            return;
        }
        basis
            .par_chunks_mut(width)
            .zip(us)
            .with_min_len(BASIS_MIN_TASK)
            .for_each_init(
                || self.jacobian.pass(),
                |pass, (out, &u)| self.basis_rows(pass, u, out),
            );
    }

    /// The rows of the span's basis of the `u`-th tracked observation's
    /// strings into `basis` (a string's after another's; zero where the
    /// row has weight 0).
    fn basis_rows(
        &self,
        pass: &mut crate::model::identify::DataJacobianPass<'_>,
        u: usize,
        basis: &mut [f64],
    ) {
        let dims = self.span.dims();
        basis.fill(0.0);
        pass.rows_of(u, |i, own, shared| {
            self.span
                .basis_row(i, own, shared, &mut basis[i * dims..(i + 1) * dims]);
        });
    }

    /// The `u`-th tracked observation as the fit reads it.
    fn observed(&self, u: usize) -> Observed<'_> {
        let frame = &self.id.frame;
        let k = self.used[u];
        let o = &self.observations[k];
        let p = device_position(frame, o);
        let inputs = inputs_at(frame, o, &p);
        Observed {
            k,
            o,
            previous: k.checked_sub(1).map(|j| &self.observations[j]),
            p,
            total_tension_n: total_tension_n(frame.layout.active, &inputs.tension_mn),
            inputs,
            // The body's turn as the device frame sees it, once per row.
            body_in_device: o.tracker_rotation.map(|body| body_in_device(frame, &body)),
        }
    }

    /// String `i`'s row of the `u`-th tracked observation (`at`); `None`
    /// without a context (every string index has one).
    fn row(&self, u: usize, at: &Observed<'_>, i: usize) -> Option<Row> {
        let id = self.id;
        let p = at.p;
        let home = self.homes.get(i)?.as_ref()?;
        let ctx = EffectContext::at_home(home, &id.laws, &at.inputs, i, at.total_tension_n)?;
        let d = [
            p[0] - id.frame.anchors[i][0],
            p[1] - id.frame.anchors[i][1],
            p[2] - id.frame.anchors[i][2],
        ];
        let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let up = [d[0] / length, d[1] / length, d[2] / length];
        let speed = match at.previous {
            Some(q) if at.o.t_s > q.t_s => {
                let before = payout_f64(&id.laws[i], q.inputs.counts[i]);
                (ctx.payout_mm - before) / (at.o.t_s - q.t_s)
            }
            _ => 0.0,
        };
        Some(Row {
            obs: at.k,
            string: i,
            weight: self.jacobian.weights()[u][i],
            ctx,
            length,
            speed,
            position: p,
            marker_column: at.body_in_device.map(|m| marker_column(&m, &up)),
            scale_gradient: -(up[0] * p[0] + up[1] * p[1] + up[2] * p[2]) / id.frame.room_scale,
        })
    }
}

/// `R^T R_body / s` (`R`, `s`: the room transform), the rows of a planar
/// device's normal zeroed (its meeting point stays in its plane): how the
/// meeting point, `device_from_room(p - R_body d)`, moves against the
/// tracked body's origin `d` (body frame).
fn body_in_device(frame: &Frame<f64>, body: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let r = &frame.room_rotation;
    core::array::from_fn(|k| {
        core::array::from_fn(|j| {
            if frame.layout.planar && k == 2 {
                0.0
            } else {
                (0..3).map(|m| r[m][k] * body[m][j]).sum::<f64>() / frame.room_scale
            }
        })
    })
}

/// `d length / d marker` of a string whose unit direction (anchor to
/// end-effector) is `up`, for the body's turn `body_in_device`
/// ([`body_in_device`]): the string shortens by `up . M d`.
fn marker_column(body_in_device: &[[f64; 3]; 3], up: &[f64; 3]) -> [f64; 3] {
    core::array::from_fn(|j| (0..3).map(|k| up[k] * body_in_device[k][j]).sum::<f64>())
}
