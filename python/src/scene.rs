//! `diffluid.Scene`: a validated scene (a scene file, TOML text, or a built-in name).

use crate::convert::to_py_object;
use crate::errors::{run, value_error};
use crate::loss::BodyTargetLoss;
use diffluid::experiments::scene::BUILTIN_SCENES;
use diffluid::Scene as RScene;
use pyo3::prelude::*;
use std::path::{Path, PathBuf};

/// What `Scene.__reduce__` returns: `Scene.from_json` and its arguments (the JSON, the base
/// folder).
type Reduced<'py> = (Bound<'py, PyAny>, (String, Option<String>));

/// A scene: the tank, the liquid, the bodies, the solver settings, and optionally a
/// `[loss]` and an `[optimize]` section. Build one with :meth:`Scene.from_file`,
/// :meth:`Scene.from_toml`, :meth:`Scene.builtin` or :meth:`Scene.load` (a path or a
/// built-in name, as the CLI takes it). Scenes pickle (as JSON), so they can be sent to Ray
/// tasks.
#[pyclass(module = "diffluid._diffluid", name = "Scene")]
#[derive(Clone)]
pub struct Scene {
    pub(crate) inner: RScene,
}

#[pymethods]
impl Scene {
    /// Reads and validates a scene file (TOML). Relative mesh paths start from its folder.
    ///
    /// Raises FileNotFoundError/OSError when the file cannot be read and ValueError when it
    /// is not a valid scene (the message names the key and line).
    #[staticmethod]
    fn from_file(py: Python<'_>, path: PathBuf) -> PyResult<Scene> {
        run(py, || RScene::from_file(&path)).map(|inner| Scene { inner })
    }

    /// Parses and validates a scene from TOML text. `origin` names it in error messages;
    /// relative mesh paths start from `base_dir` (default: the current folder).
    #[staticmethod]
    #[pyo3(signature = (text, origin = "<string>", base_dir = None))]
    fn from_toml(
        py: Python<'_>,
        text: &str,
        origin: &str,
        base_dir: Option<PathBuf>,
    ) -> PyResult<Scene> {
        let base = base_dir.unwrap_or_else(|| PathBuf::from("."));
        run(py, || RScene::from_toml_in(text, origin, base)).map(|inner| Scene { inner })
    }

    /// A scene shipped with diffluid, by name (see :meth:`Scene.builtin_names`).
    #[staticmethod]
    fn builtin(py: Python<'_>, name: &str) -> PyResult<Scene> {
        run(py, || RScene::builtin(name)).map(|inner| Scene { inner })
    }

    /// A scene file's path or a built-in scene's name, resolved as the CLI resolves its
    /// `SCENE` argument: an existing path, or else a built-in name when the argument has no
    /// extension.
    #[staticmethod]
    fn load(py: Python<'_>, scene: PathBuf) -> PyResult<Scene> {
        run(py, || {
            let name = scene.to_string_lossy();
            if !scene.exists()
                && scene.extension().is_none()
                && BUILTIN_SCENES.iter().any(|(n, _)| *n == name)
            {
                RScene::builtin(&name)
            } else {
                RScene::from_file(&scene)
            }
        })
        .map(|inner| Scene { inner })
    }

    /// The names of the built-in scenes.
    #[staticmethod]
    fn builtin_names() -> Vec<&'static str> {
        BUILTIN_SCENES.iter().map(|(n, _)| *n).collect()
    }

    /// The scene's name.
    #[getter]
    fn name(&self) -> String {
        self.inner.name.clone()
    }

    /// Its description.
    #[getter]
    fn description(&self) -> String {
        self.inner.description.clone()
    }

    /// Steps a run takes (`time.steps`); settable (at least 1).
    #[getter]
    fn steps(&self) -> usize {
        self.inner.time.steps
    }

    #[setter]
    fn set_steps(&mut self, steps: usize) -> PyResult<()> {
        if steps == 0 {
            return Err(value_error("time.steps: must be at least 1"));
        }
        self.inner.time.steps = steps;
        Ok(())
    }

    /// The fixed time step Δt, s.
    #[getter]
    fn dt(&self) -> f64 {
        self.inner.time.dt
    }

    /// Cell side, m.
    #[getter]
    fn dx(&self) -> f64 {
        self.inner.domain.dx
    }

    /// Tank extent (x, y up, z), m.
    #[getter]
    fn size(&self) -> [f64; 3] {
        self.inner.domain.size
    }

    /// The bodies' names, in order.
    #[getter]
    fn body_names(&self) -> Vec<String> {
        (0..self.inner.body.len()).map(|i| self.inner.body[i].name_or_default(i)).collect()
    }

    /// Whether the liquid surface is held fixed (`solver.freeze_surface`); settable. The
    /// `[optimize]` section's own `freeze_surface` applies to :func:`diffluid.optimize` only.
    #[getter]
    fn freeze_surface(&self) -> bool {
        self.inner.solver.freeze_surface
    }

    #[setter]
    fn set_freeze_surface(&mut self, on: bool) {
        self.inner.solver.freeze_surface = on;
    }

    /// Whether the scene has a `[loss]` section.
    #[getter]
    fn has_loss(&self) -> bool {
        self.inner.loss.is_some()
    }

    /// The scene's `[loss]` as a BodyTargetLoss (None without one).
    #[getter]
    fn loss(&self) -> Option<BodyTargetLoss> {
        self.inner.loss().as_ref().map(BodyTargetLoss::from_rust)
    }

    /// The scene's `[optimize]` section as a dict (params, optimizer {kind, learning_rate,
    /// ...}, epochs, freeze_surface, ...), or None.
    #[getter]
    fn optimize_spec<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.inner.optimize.as_ref().map(|o| to_py_object(py, o)).transpose()
    }

    /// The scene as JSON (every number exact): what pickling sends.
    fn to_json(&self) -> String {
        serde_json::to_string(&self.inner).expect("a scene serialises")
    }

    /// A scene from :meth:`Scene.to_json`'s text, validated again; relative mesh paths start
    /// from `base_dir`.
    #[staticmethod]
    #[pyo3(signature = (text, base_dir = None))]
    fn from_json(py: Python<'_>, text: &str, base_dir: Option<PathBuf>) -> PyResult<Scene> {
        let mut inner: RScene = serde_json::from_str(text)
            .map_err(|e| value_error(format!("not a diffluid scene in JSON: {e}")))?;
        inner.base_dir = base_dir;
        run(py, || inner.check().map(|()| inner)).map(|inner| Scene { inner })
    }

    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Reduced<'py>> {
        let this = slf.borrow();
        let from_json = slf.get_type().getattr("from_json")?;
        let base = this.inner.base_dir.as_deref().map(|p: &Path| p.display().to_string());
        Ok((from_json, (this.to_json(), base)))
    }

    fn __copy__(&self) -> Scene {
        self.clone()
    }

    fn __deepcopy__(&self, _memo: &Bound<'_, PyAny>) -> Scene {
        self.clone()
    }

    fn __eq__(&self, other: &Scene) -> bool {
        self.inner == other.inner
    }

    fn __repr__(&self) -> String {
        let d = &self.inner.domain;
        format!(
            "Scene({:?}, size={:?}, dx={}, steps={}, bodies={:?})",
            self.inner.name,
            d.size,
            d.dx,
            self.inner.time.steps,
            self.body_names()
        )
    }
}
