//! L-BFGS for [`Optimization`] (feature `lbfgs`): argmin's L-BFGS with its Moré–Thuente
//! line search, driven one iteration per epoch through argmin's `Solver` trait (`init`, then
//! `next_iter`), the loop argmin's `Executor` would run, so that each epoch is recorded,
//! checked and checkpointed like a gradient-descent epoch. Its state (correction pairs, line
//! search, iteration state) is saved with argmin's serde support.

use super::optimize::{Checkpoint, EpochRecord, Optimization, OptimizerState, Outcome};
use super::scene::OptimizerSpec;
use crate::error::{Error, Result};
use argmin::core::{CostFunction, Gradient, IterState, Problem, Solver, State, TerminationStatus};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;
use serde::Serialize;
use std::cell::{Cell, RefCell};
use std::ops::ControlFlow;
use std::path::Path;

impl Optimization {
    /// L-BFGS: one argmin iteration per epoch, the state checkpointed after each.
    pub(super) fn run_lbfgs(
        &self,
        checkpoint: Option<&Path>,
        mut ck: Checkpoint,
        mut on_epoch: impl FnMut(&EpochRecord) -> ControlFlow<()>,
    ) -> Result<Outcome> {
        let evaluations = Cell::new(ck.evaluations);
        let failure = RefCell::new(None);
        let mut problem = Problem::new(Objective {
            problem: self,
            evaluations: &evaluations,
            failure: &failure,
            cache: RefCell::new(Vec::new()),
            epoch: Cell::new(ck.next_epoch),
        });
        let restored = match &ck.optimizer {
            OptimizerState::Lbfgs { solver, state } => {
                let read = from_toml::<LbfgsSolver>(solver)
                    .and_then(|s| Ok((s, from_toml::<LbfgsState>(state)?)));
                Some(read.map_err(|message| Error::Checkpoint {
                    path: ck.source.clone().unwrap_or_default(),
                    message,
                })?)
            }
            _ => None,
        };
        let (mut solver, mut state) = match restored {
            Some(x) => x,
            None => {
                let mut solver = new_lbfgs(&self.optimizer)?;
                let start = IterState::new()
                    .param(self.to_vector(&ck.params))
                    .max_iters(self.epochs as u64);
                match solver.init(&mut problem, start) {
                    Ok((mut state, _)) => {
                        state.update();
                        (solver, state)
                    }
                    Err(e) => {
                        let reason = failure.borrow().clone().unwrap_or_else(|| e.to_string());
                        return Ok(Outcome {
                            history: ck.history,
                            params: ck.params,
                            final_loss: f64::NAN,
                            stopped: Some(reason),
                            converged: None,
                            evaluations: evaluations.get(),
                        });
                    }
                }
            }
        };
        ck.evaluations = evaluations.get();
        let mut stopped = None;
        let mut converged = None;
        while ck.next_epoch < self.epochs {
            // The state holds this epoch's parameters, loss and gradient.
            if ck.next_epoch > 0 {
                let status =
                    <_ as Solver<Objective<'_>, LbfgsState>>::terminate(&mut solver, &state);
                if let TerminationStatus::Terminated(reason) = status {
                    converged = Some(format!("epoch {}: {reason}", ck.next_epoch));
                    break;
                }
            }
            let x = state.get_param().expect("L-BFGS keeps its parameters").clone();
            let loss = state.get_cost();
            let g = state.get_gradient().expect("L-BFGS keeps its gradient");
            let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
            let params = self.from_vector(&x);
            if let Some(m) = self.record_epoch(&mut ck, (loss, norm), params, &mut on_epoch) {
                stopped = Some(m);
                break;
            }
            problem.problem.as_ref().expect("the objective").epoch.set(ck.next_epoch);
            // argmin ends an iteration whose line search failed with a termination reason; an
            // error of the gradient after it comes back as an error.
            let (next, error) = match solver.next_iter(&mut problem, state) {
                Ok((next, _)) => (next, None),
                Err(e) => (IterState::new(), Some(e.to_string())),
            };
            state = next;
            ck.evaluations = evaluations.get();
            if error.is_some() || state.terminated() {
                let argmin_reason = error.unwrap_or_else(|| {
                    state.get_termination_reason().map(|r| r.to_string()).unwrap_or_default()
                });
                let reason = failure
                    .borrow()
                    .clone()
                    .unwrap_or_else(|| format!("epoch {}: {argmin_reason}", ck.next_epoch));
                stopped = Some(if reason.contains("kept the last good parameters") {
                    reason
                } else {
                    format!("{reason}; kept the last good parameters")
                });
                break;
            }
            state.update();
            state.increment_iter();
            ck.next_epoch += 1;
            ck.params = self.from_vector(state.get_param().expect("L-BFGS keeps its parameters"));
            ck.optimizer =
                OptimizerState::Lbfgs { solver: to_toml(&solver), state: to_toml(&state) };
            if let Some(path) = checkpoint {
                ck.save(path)?;
            }
        }
        let (params, final_loss) = match (&stopped, &converged) {
            (Some(_), _) => {
                let last = ck.history.last();
                (
                    last.map(|r| r.params).unwrap_or(ck.params),
                    last.map(|r| r.loss).unwrap_or(f64::NAN),
                )
            }
            _ => (ck.params, state.get_cost()),
        };
        Ok(Outcome {
            history: ck.history,
            params,
            final_loss,
            stopped,
            converged,
            evaluations: ck.evaluations,
        })
    }
}

impl Optimization {
    /// The L-BFGS part of [`Optimization::check_checkpoint`]: argmin's iteration state holds
    /// finite parameters and gradient of the problem's size, at iteration `next_epoch`, not
    /// terminated, the same parameters as the checkpoint's; the solver holds at most `memory`
    /// finite correction pairs of that size and is otherwise configured exactly as the
    /// scene's L-BFGS (memory, tolerances, line search).
    pub(super) fn check_lbfgs(
        &self,
        solver: &str,
        state: &str,
        c: &Checkpoint,
    ) -> std::result::Result<(), String> {
        let n = 3 * self.params.len();
        let vector = |key: &str, x: Option<&Vector>| -> std::result::Result<(), String> {
            match x {
                None => Err(format!("{key} is missing")),
                Some(x) if x.len() != n => {
                    Err(format!("{key} has {} numbers; the scene optimises {n}", x.len()))
                }
                Some(x) if !x.iter().all(|a| a.is_finite()) => Err(format!("{key} is not finite")),
                Some(_) => Ok(()),
            }
        };

        let key = "optimizer.Lbfgs.state";
        let st: LbfgsState = toml::from_str(state)
            .map_err(|e| format!("{key}: not argmin's L-BFGS state: {}", one_line(&e)))?;
        vector(&format!("{key}: param"), st.get_param())?;
        vector(&format!("{key}: grad"), st.get_gradient())?;
        for (name, x) in [
            ("best_param", st.get_best_param()),
            ("prev_param", st.get_prev_param()),
            ("prev_best_param", st.get_prev_best_param()),
        ] {
            if x.is_some() {
                vector(&format!("{key}: {name}"), x)?;
            }
        }
        if !st.get_cost().is_finite() {
            return Err(format!("{key}: cost is {}", st.get_cost()));
        }
        if st.get_iter() != c.next_epoch as u64 {
            return Err(format!(
                "{key}: iter is {}, but next_epoch is {}",
                st.get_iter(),
                c.next_epoch
            ));
        }
        if st.terminated() {
            return Err(format!("{key}: the run it holds has ended"));
        }
        let at = self.from_vector(st.get_param().expect("checked"));
        if at != c.params {
            return Err(format!("params are not those of {key} (its param)"));
        }

        let key = "optimizer.Lbfgs.solver";
        let unreadable =
            |e: toml::de::Error| format!("{key}: not argmin's L-BFGS: {}", one_line(&e));
        let mut saved: toml::Table = toml::from_str(solver).map_err(unreadable)?;
        let mut fresh: toml::Table =
            toml::from_str(&to_toml(&new_lbfgs(&self.optimizer).map_err(|e| e.to_string())?))
                .expect("argmin's solver reads back");
        let memory = fresh.get("m").and_then(toml::Value::as_integer).unwrap_or(0);
        let mut pairs = [0, 0];
        for (k, name) in ["s", "y"].into_iter().enumerate() {
            fresh.remove(name);
            let Some(list) = saved.remove(name) else {
                return Err(format!("{key}: {name} is missing"));
            };
            let vectors: Vec<Vector> =
                list.try_into().map_err(|_| format!("{key}: {name} is not a list of vectors"))?;
            for v in &vectors {
                vector(&format!("{key}: {name}"), Some(v))?;
            }
            pairs[k] = vectors.len();
        }
        if pairs[0] != pairs[1] || pairs[0] as i64 > memory {
            return Err(format!(
                "{key}: s and y hold {} and {} correction pairs (the same number, at most \
                 memory = {memory}, expected)",
                pairs[0], pairs[1]
            ));
        }
        let search = |t: &mut toml::Table| {
            t.get_mut("linesearch")
                .and_then(toml::Value::as_table_mut)
                .and_then(|l| l.remove("search_direction"))
        };
        if let Some(d) = search(&mut saved) {
            let d: Vector = d
                .try_into()
                .map_err(|_| format!("{key}: linesearch.search_direction is not a vector"))?;
            vector(&format!("{key}: linesearch.search_direction"), Some(&d))?;
        }
        search(&mut fresh);
        if let Some((name, was, now)) = table_difference("", &saved, &fresh) {
            return Err(format!("{key}: {name} is {was}; the scene's L-BFGS has {now}"));
        }
        // What is left is checked: argmin reads it back.
        from_toml::<LbfgsSolver>(solver).map_err(|e| format!("{key}: {e}"))?;
        Ok(())
    }
}

/// A toml error's message on one line.
fn one_line(e: &toml::de::Error) -> String {
    e.message().trim().replace('\n', " ")
}

/// The first dotted key at which two TOML tables differ (compared as TOML text, so NaN
/// equals NaN), with both values.
fn table_difference(
    path: &str,
    a: &toml::Table,
    b: &toml::Table,
) -> Option<(String, String, String)> {
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter().find_map(|k| {
        let p = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
        match (a.get(k), b.get(k)) {
            (Some(toml::Value::Table(x)), Some(toml::Value::Table(y))) => {
                table_difference(&p, x, y)
            }
            (x, y) => {
                let text = |v: Option<&toml::Value>| v.map_or("nothing".into(), |v| v.to_string());
                let (x, y) = (text(x), text(y));
                (x != y).then_some((p, x, y))
            }
        }
    })
}

type Vector = Vec<f64>;
type LbfgsState = IterState<Vector, Vector, (), (), (), f64>;

/// argmin's L-BFGS with its Moré–Thuente line search.
type LbfgsSolver = LBFGS<MoreThuenteLineSearch<Vector, Vector, f64>, Vector, Vector, f64>;

type ArgminResult<T> = std::result::Result<T, argmin::core::Error>;

fn new_lbfgs(spec: &OptimizerSpec) -> Result<LbfgsSolver> {
    let OptimizerSpec::Lbfgs { memory, tolerance_grad, tolerance_cost } = spec else {
        unreachable!("an L-BFGS spec")
    };
    LBFGS::new(MoreThuenteLineSearch::new(), *memory)
        .with_tolerance_grad(*tolerance_grad)
        .and_then(|s| s.with_tolerance_cost(*tolerance_cost))
        .map_err(|e| Error::InvalidScene {
            origin: "optimize.optimizer".into(),
            message: e.to_string(),
        })
}

fn to_toml<T: Serialize>(x: &T) -> String {
    toml::to_string(x).expect("argmin's state serialises")
}

/// argmin's state read back from a checkpoint; [`Optimization::check_lbfgs`] has checked it.
fn from_toml<T: serde::de::DeserializeOwned>(text: &str) -> std::result::Result<T, String> {
    toml::from_str(text).map_err(|e| format!("L-BFGS state unreadable: {}", one_line(&e)))
}

/// The loss as argmin sees it. The line searches ask for the loss and then the gradient at
/// the same point, and L-BFGS asks again for the gradient at the point it accepts: one
/// adjoint run gives both, so the last few are kept and a repeated point costs nothing.
struct Objective<'a> {
    problem: &'a Optimization,
    evaluations: &'a Cell<usize>,
    /// Why the last evaluation failed (argmin turns a failed line search into a reason of
    /// its own; this keeps ours).
    failure: &'a RefCell<Option<String>>,
    cache: RefCell<Vec<(Vector, f64, Vector)>>,
    epoch: Cell<usize>,
}

impl Objective<'_> {
    fn eval(&self, x: &Vector) -> ArgminResult<(f64, Vector)> {
        if let Some((_, f, g)) = self.cache.borrow().iter().find(|(p, _, _)| p == x) {
            return Ok((*f, g.clone()));
        }
        self.evaluations.set(self.evaluations.get() + 1);
        let epoch = self.epoch.get();
        let fail = |m: String| {
            *self.failure.borrow_mut() = Some(m.clone());
            argmin::core::Error::msg(m)
        };
        let (f, g) =
            self.problem.evaluate_vector(x).map_err(|e| fail(format!("epoch {epoch}: {e}")))?;
        let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
        if let Some(m) = self.problem.stop_message(epoch, f, norm) {
            return Err(fail(m));
        }
        let mut cache = self.cache.borrow_mut();
        if cache.len() == 4 {
            cache.remove(0);
        }
        cache.push((x.clone(), f, g.clone()));
        Ok((f, g))
    }
}

impl CostFunction for Objective<'_> {
    type Param = Vector;
    type Output = f64;
    fn cost(&self, x: &Vector) -> ArgminResult<f64> {
        Ok(self.eval(x)?.0)
    }
}

impl Gradient for Objective<'_> {
    type Param = Vector;
    type Gradient = Vector;
    fn gradient(&self, x: &Vector) -> ArgminResult<Vector> {
        Ok(self.eval(x)?.1)
    }
}
