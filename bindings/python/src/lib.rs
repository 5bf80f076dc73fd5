//! Python bindings of pir2 (module `pir2._pir2`, re-exported by the `pir2` package).
//!
//! Everything here is a thin layer over `pir2-schedule` (staircase, streaming buffer,
//! training draws, seeded generator, GR00T N1.7's flow-time law) and `pir2-runtime`'s
//! latency window: the numbers are computed by the Rust code, so the same seed gives the
//! same bits as Rust. Every invalid input is a Rust `pir2_schedule::Error`, raised in
//! Python as `ValueError` with the error's text; nothing here panics on user input.
//!
//! One file on purpose: it is the Python module `pir2._pir2` whole, one section per class,
//! read side by side with the module's stub (`python/pir2/__init__.pyi`); every section is a
//! thin layer over one Rust type, and all of them share the argument helpers at the top that
//! turn every invalid input into that one `ValueError`.

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use pir2_runtime::policy::{Policy, Recipe};
use pir2_runtime::LatencyWindow;
use pir2_schedule::train::{self, DelayDist, Draw, FrontVisibility, PiR2Draws, TrainSchedule};
use pir2_schedule::{Alignment, Error, FrontMode, Staircase, StreamBuffer, StreamConfig};

// ---------------------------------------------------------------------------------------
// Argument helpers: every failure is a `pir2_schedule::Error` → `ValueError(text)`.
// ---------------------------------------------------------------------------------------

fn err(e: Error) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A recipe dict naming a field `Recipe` does not have is an error listing the fields (serde
/// would ignore it, and the schedule would silently be another one than asked for).
fn check_recipe_keys(given: &serde_json::Value) -> PyResult<()> {
    let known = serde_json::to_value(Recipe::default())
        .map_err(|e| invalid("recipe", e.to_string()))?;
    if let (Some(given), Some(known)) = (given.as_object(), known.as_object()) {
        if let Some(k) = given.keys().find(|k| !known.contains_key(*k)) {
            let fields: Vec<&str> = known.keys().map(String::as_str).collect();
            return Err(invalid(
                "recipe",
                format!("unknown field {k:?}; the fields are {}", fields.join(", ")),
            ));
        }
    }
    Ok(())
}

fn invalid(field: &'static str, message: impl Into<String>) -> PyErr {
    err(Error::Invalid {
        field,
        message: message.into(),
    })
}

/// A non-negative integer argument (Python ints can be negative; `usize` cannot).
fn count(field: &'static str, v: i64) -> PyResult<usize> {
    usize::try_from(v).map_err(|_| invalid(field, format!("must be >= 0, got {v}")))
}

fn opt_count(field: &'static str, v: Option<i64>) -> PyResult<Option<usize>> {
    v.map(|v| count(field, v)).transpose()
}

/// A seed: an integer in `[0, 2^64)`.
fn seed_arg(seed: &Bound<'_, PyAny>) -> PyResult<u64> {
    seed.extract::<u64>().map_err(|_| {
        let shown = seed
            .repr()
            .map(|r| r.to_string())
            .unwrap_or_else(|_| "?".into());
        invalid(
            "seed",
            format!("must be an integer in [0, 2^64) or a pir2.Rng, got {shown}"),
        )
    })
}

fn alignment_arg(s: &str) -> PyResult<Alignment> {
    match s {
        "fresh" => Ok(Alignment::Fresh),
        "paper" => Ok(Alignment::Paper),
        _ => Err(invalid(
            "alignment",
            format!("must be \"fresh\" or \"paper\", got {s:?}"),
        )),
    }
}

fn front_mode_arg(s: &str) -> PyResult<FrontMode> {
    match s {
        "visible" => Ok(FrontMode::Visible),
        "hidden" => Ok(FrontMode::Hidden),
        _ => Err(invalid(
            "front",
            format!("must be \"visible\" or \"hidden\", got {s:?}"),
        )),
    }
}

fn front_mode_name(f: FrontMode) -> &'static str {
    match f {
        FrontMode::Visible => "visible",
        FrontMode::Hidden => "hidden",
    }
}

/// An array-like converted to C-contiguous `float32`, checked against `shape`: a different
/// element count is `Error::Length` (the Rust text of a wrong slice length), the same count
/// in another shape is `Error::Invalid`. A flat array of the right length is accepted.
fn f32_input(
    py: Python<'_>,
    obj: &Bound<'_, PyAny>,
    what: &'static str,
    shape: &[usize],
) -> PyResult<Vec<f32>> {
    let (v, got) = f32_any(py, obj)?;
    let expected: usize = shape.iter().product();
    if v.len() != expected {
        return Err(err(Error::Length {
            what,
            expected,
            got: v.len(),
        }));
    }
    if got.len() > 1 && got != shape {
        return Err(invalid(
            what,
            format!("has shape {got:?}, expected {shape:?}"),
        ));
    }
    Ok(v)
}

/// Any array-like as C-contiguous `float32` data and its shape.
fn f32_any(py: Python<'_>, obj: &Bound<'_, PyAny>) -> PyResult<(Vec<f32>, Vec<usize>)> {
    let np = py.import("numpy")?;
    let a = np.call_method1("ascontiguousarray", (obj, "float32"))?;
    let a: PyReadonlyArrayDyn<'_, f32> = a.extract()?;
    let shape = a.shape().to_vec();
    let v = a.as_slice()?.to_vec();
    Ok((v, shape))
}

fn arr1<'py, T: numpy::Element>(py: Python<'py>, v: Vec<T>) -> Bound<'py, PyArray1<T>> {
    Array1::from_vec(v).into_pyarray(py)
}

fn arr2<'py, T: numpy::Element>(
    py: Python<'py>,
    v: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArray2<T>>> {
    Array2::from_shape_vec((rows, cols), v)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

// ---------------------------------------------------------------------------------------
// Rng
// ---------------------------------------------------------------------------------------

/// Seeded xoshiro256++ generator (seeded by SplitMix64), the generator of every pir2 draw.
///
/// `Rng(seed)` gives exactly the stream of Rust's `pir2_schedule::Rng::new(seed)`: same
/// seed, same bits, on every platform. Pass it to a draw to continue one stream across
/// calls (the draw advances it in place, as Rust's `&mut Rng` does).
#[pyclass(module = "pir2._pir2", name = "Rng")]
#[derive(Debug, Clone)]
struct PyRng {
    inner: pir2_schedule::Rng,
}

#[pymethods]
impl PyRng {
    /// A generator seeded from `seed` (an integer in `[0, 2^64)`).
    #[new]
    fn new(seed: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(Self {
            inner: pir2_schedule::Rng::new(seed_arg(seed)?),
        })
    }

    /// An independent stream derived from `seed` and a stream id (Rust `Rng::derive`).
    #[staticmethod]
    fn derive(seed: &Bound<'_, PyAny>, stream: &Bound<'_, PyAny>) -> PyResult<Self> {
        let stream = stream
            .extract::<u64>()
            .map_err(|_| invalid("stream", "must be an integer in [0, 2^64)"))?;
        Ok(Self {
            inner: pir2_schedule::Rng::derive(seed_arg(seed)?, stream),
        })
    }

    /// A generator continuing from a saved `state` (four integers in `[0, 2^64)`, not all
    /// zero), as Rust `Rng::from_state`.
    #[staticmethod]
    fn from_state(state: &Bound<'_, PyAny>) -> PyResult<Self> {
        let state: [u64; 4] = state
            .extract()
            .map_err(|_| invalid("state", "must be four integers in [0, 2^64)"))?;
        pir2_schedule::Rng::from_state(state)
            .map(|inner| Self { inner })
            .ok_or_else(|| invalid("state", "the all-zero state is not a valid xoshiro state"))
    }

    /// The generator's full state, four unsigned 64-bit integers (save it to continue the
    /// same stream later).
    #[getter]
    fn state(&self) -> [u64; 4] {
        self.inner.state()
    }

    /// Next 64 random bits: an `int`, or a `uint64` array of `size` values.
    #[pyo3(signature = (size=None))]
    fn next_u64(&mut self, py: Python<'_>, size: Option<i64>) -> PyResult<Py<PyAny>> {
        match opt_count("size", size)? {
            None => Ok(self.inner.next_u64().into_pyobject(py)?.into_any().unbind()),
            Some(n) => {
                let v: Vec<u64> = (0..n).map(|_| self.inner.next_u64()).collect();
                Ok(arr1(py, v).into_any().unbind())
            }
        }
    }

    /// Uniform in `[0, 1)` with 24 bits (Rust `Rng::uniform`, `f32`): a `float`, or a
    /// `float32` array of `size` values drawn in order.
    #[pyo3(signature = (size=None))]
    fn uniform(&mut self, py: Python<'_>, size: Option<i64>) -> PyResult<Py<PyAny>> {
        match opt_count("size", size)? {
            None => Ok(self.inner.uniform().into_pyobject(py)?.into_any().unbind()),
            Some(n) => {
                let v: Vec<f32> = (0..n).map(|_| self.inner.uniform()).collect();
                Ok(arr1(py, v).into_any().unbind())
            }
        }
    }

    /// Uniform in `[0, 1)` with 53 bits (Rust `Rng::uniform_f64`): a `float`, or a
    /// `float64` array of `size` values.
    #[pyo3(signature = (size=None))]
    fn uniform_f64(&mut self, py: Python<'_>, size: Option<i64>) -> PyResult<Py<PyAny>> {
        match opt_count("size", size)? {
            None => Ok(self
                .inner
                .uniform_f64()
                .into_pyobject(py)?
                .into_any()
                .unbind()),
            Some(n) => {
                let v: Vec<f64> = (0..n).map(|_| self.inner.uniform_f64()).collect();
                Ok(arr1(py, v).into_any().unbind())
            }
        }
    }

    /// Uniform integer in `[0, n)` (`n >= 1`), unbiased (Rust `Rng::below`).
    fn below(&mut self, n: &Bound<'_, PyAny>) -> PyResult<u64> {
        let n = n
            .extract::<u64>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| invalid("n", "must be an integer in [1, 2^64)"))?;
        Ok(self.inner.below(n))
    }

    /// Standard normal sample (Rust `Rng::normal`, ziggurat, `f32`): a `float`, or a
    /// `float32` array of `size` values (Rust `Rng::fill_normal`).
    #[pyo3(signature = (size=None))]
    fn normal(&mut self, py: Python<'_>, size: Option<i64>) -> PyResult<Py<PyAny>> {
        match opt_count("size", size)? {
            None => Ok(self.inner.normal().into_pyobject(py)?.into_any().unbind()),
            Some(n) => {
                let mut v = vec![0.0f32; n];
                self.inner.fill_normal(&mut v);
                Ok(arr1(py, v).into_any().unbind())
            }
        }
    }

    fn __repr__(&self) -> String {
        format!("Rng(state={:?})", self.inner.state())
    }
}

/// Run `f` on the generator a Python argument names: a `pir2.Rng` (advanced in place) or
/// an integer seed (a fresh `Rng::new(seed)`).
fn with_rng<R>(
    rng: &Bound<'_, PyAny>,
    f: impl FnOnce(&mut pir2_schedule::Rng) -> PyResult<R>,
) -> PyResult<R> {
    if let Ok(mut r) = rng.extract::<PyRefMut<'_, PyRng>>() {
        f(&mut r.inner)
    } else {
        let mut r = pir2_schedule::Rng::new(seed_arg(rng)?);
        f(&mut r)
    }
}

// ---------------------------------------------------------------------------------------
// GR00T N1.7's flow-time law
// ---------------------------------------------------------------------------------------

/// Flow times `τ` from GR00T N1.7's training law, `τ = 0.999·(1 − B)` with
/// `B ~ Beta(1.5, 1)` (Rust `pir2_schedule::train::gr00t_n17_tau`; 0 = noise, 1 = clean).
///
/// `rng` is a `pir2.Rng` (advanced in place) or an integer seed. Returns one `float`, or a
/// `float32` array of `size` draws (the same bits as `size` calls in Rust).
#[pyfunction]
#[pyo3(signature = (rng, size=None))]
fn gr00t_n17_tau(py: Python<'_>, rng: &Bound<'_, PyAny>, size: Option<i64>) -> PyResult<Py<PyAny>> {
    let size = opt_count("size", size)?;
    with_rng(rng, |r| match size {
        None => Ok(train::gr00t_n17_tau(r)
            .into_pyobject(py)?
            .into_any()
            .unbind()),
        Some(n) => {
            let v: Vec<f32> = (0..n).map(|_| train::gr00t_n17_tau(r)).collect();
            Ok(arr1(py, v).into_any().unbind())
        }
    })
}

/// The CDF of GR00T N1.7's flow-time law, `1 − (1 − t/s)^α` on `[0, s]`, elementwise on a
/// float or an array (returns `float64`).
#[pyfunction]
fn gr00t_n17_tau_cdf(py: Python<'_>, t: &Bound<'_, PyAny>) -> PyResult<Py<PyAny>> {
    if let Ok(x) = t.extract::<f64>() {
        return Ok(train::gr00t_n17_tau_cdf(x)
            .into_pyobject(py)?
            .into_any()
            .unbind());
    }
    let np = py.import("numpy")?;
    let a = np.call_method1("ascontiguousarray", (t, "float64"))?;
    let a: PyReadonlyArrayDyn<'_, f64> = a.extract()?;
    let shape = a.shape().to_vec();
    let v: Vec<f64> = a
        .as_slice()?
        .iter()
        .map(|&x| train::gr00t_n17_tau_cdf(x))
        .collect();
    let out = arr1(py, v);
    Ok(out.call_method1("reshape", (shape,))?.unbind())
}

// ---------------------------------------------------------------------------------------
// Staircase
// ---------------------------------------------------------------------------------------

/// A validated staircase `τ*` (per-position noise level, 0 = noise, 1 = clean) for chunk
/// length `horizon` = H, delay `delay` = d and `n` NFEs per action.
///
/// A clean front of `d` in-flight actions, a ramp, a tail of noise. `n=None` is the full
/// ramp (`n_max` for the fresh alignment; the paper alignment is always its own full ramp).
/// Invalid combinations (e.g. `d` too large for `H`, `n > n_max`) raise `ValueError` with
/// the Rust error's text.
#[pyclass(module = "pir2._pir2", name = "Staircase", frozen, eq)]
#[derive(Debug, Clone, PartialEq)]
struct PyStaircase {
    inner: Staircase,
}

#[pymethods]
impl PyStaircase {
    /// `Staircase(horizon, delay, n=None, alignment="fresh")` (Rust `Staircase::new`).
    #[new]
    #[pyo3(signature = (horizon, delay, n=None, alignment="fresh"))]
    fn new(horizon: i64, delay: i64, n: Option<i64>, alignment: &str) -> PyResult<Self> {
        let s = Staircase::new(
            count("H", horizon)?,
            count("d", delay)?,
            opt_count("n", n)?,
            alignment_arg(alignment)?,
        )
        .map_err(err)?;
        Ok(Self { inner: s })
    }

    /// The fresh-alignment staircase (the default): ramp of `n·max(d,1) − 1` slots.
    #[staticmethod]
    #[pyo3(signature = (horizon, delay, n=None))]
    fn fresh(horizon: i64, delay: i64, n: Option<i64>) -> PyResult<Self> {
        Self::new(horizon, delay, n, "fresh")
    }

    /// The paper's literal staircase: full-chunk ramp `1 − (p−d)/(H−2d)`.
    #[staticmethod]
    fn paper(horizon: i64, delay: i64) -> PyResult<Self> {
        Self::new(horizon, delay, None, "paper")
    }

    /// Largest valid `n` for `(H, d)` with the fresh alignment (0 when none is valid).
    #[staticmethod]
    fn n_max(horizon: i64, delay: i64) -> PyResult<usize> {
        Ok(Staircase::n_max(count("H", horizon)?, count("d", delay)?))
    }

    /// Chunk length `H`.
    #[getter]
    fn horizon(&self) -> usize {
        self.inner.horizon()
    }

    /// Delay `d` (front length).
    #[getter]
    fn delay(&self) -> usize {
        self.inner.delay()
    }

    /// NFEs per action `n` (resolved: the full ramp's value when built with `n=None`).
    #[getter]
    fn nfe(&self) -> usize {
        self.inner.nfe()
    }

    /// The alignment, `"fresh"` or `"paper"`.
    #[getter]
    fn alignment(&self) -> &'static str {
        self.inner.alignment().name()
    }

    /// Slots emitted per call at steady state, `max(d, 1)`.
    #[getter]
    fn emitted(&self) -> usize {
        self.inner.emitted()
    }

    /// `τ*` as a `float32` array of shape `[H]`, or `τ*_p` of one position `p` (positions
    /// `p >= H` are 0).
    #[pyo3(signature = (p=None))]
    fn tau(&self, py: Python<'_>, p: Option<i64>) -> PyResult<Py<PyAny>> {
        match p {
            Some(p) => Ok(self
                .inner
                .tau(count("p", p)?)
                .into_pyobject(py)?
                .into_any()
                .unbind()),
            None => Ok(arr1(py, self.inner.to_vec()).into_any().unbind()),
        }
    }

    /// The target after one call: the staircase shifted right by `max(d, 1)` (1 in front),
    /// as a `float32` array `[H]` or for one position `p`.
    #[pyo3(signature = (p=None))]
    fn tau_after(&self, py: Python<'_>, p: Option<i64>) -> PyResult<Py<PyAny>> {
        match p {
            Some(p) => Ok(self
                .inner
                .tau_after(count("p", p)?)
                .into_pyobject(py)?
                .into_any()
                .unbind()),
            None => {
                let v: Vec<f32> = (0..self.inner.horizon())
                    .map(|p| self.inner.tau_after(p))
                    .collect();
                Ok(arr1(py, v).into_any().unbind())
            }
        }
    }

    /// The same family (alignment, requested `n`) at another delay, `n` capped at the new
    /// delay's `n_max` (Rust `Staircase::at_delay`).
    #[pyo3(signature = (delay, requested_n=None))]
    fn at_delay(&self, delay: i64, requested_n: Option<i64>) -> PyResult<Self> {
        let s = self
            .inner
            .at_delay(count("d", delay)?, opt_count("n", requested_n)?)
            .map_err(err)?;
        Ok(Self { inner: s })
    }

    /// `τ*` as a `float32` array `[H]` (numpy protocol).
    #[pyo3(signature = (dtype=None, copy=None))]
    fn __array__(
        &self,
        py: Python<'_>,
        dtype: Option<&Bound<'_, PyAny>>,
        copy: Option<bool>,
    ) -> PyResult<Py<PyAny>> {
        let _ = copy;
        let a = arr1(py, self.inner.to_vec()).into_any();
        match dtype {
            Some(d) if !d.is_none() => Ok(a.call_method1("astype", (d,))?.unbind()),
            _ => Ok(a.unbind()),
        }
    }

    fn __len__(&self) -> usize {
        self.inner.horizon()
    }

    fn __repr__(&self) -> String {
        format!(
            "Staircase(horizon={}, delay={}, n={}, alignment={:?})",
            self.inner.horizon(),
            self.inner.delay(),
            self.inner.nfe(),
            self.inner.alignment().name()
        )
    }
}

/// Per-position `τ*` of the staircase for `(H, d, n)` as a `float32` array `[H]`
/// (shorthand for `Staircase(horizon, delay, n, alignment).tau()`).
#[pyfunction]
#[pyo3(signature = (horizon, delay, n=None, alignment="fresh"))]
fn staircase(
    py: Python<'_>,
    horizon: i64,
    delay: i64,
    n: Option<i64>,
    alignment: &str,
) -> PyResult<Py<PyArray1<f32>>> {
    let s = PyStaircase::new(horizon, delay, n, alignment)?;
    Ok(arr1(py, s.inner.to_vec()).unbind())
}

// ---------------------------------------------------------------------------------------
// Training draws
// ---------------------------------------------------------------------------------------

/// Distribution of the training delay `d` (Rust `pir2_schedule::train::DelayDist`).
///
/// `DelayDist.uniform(max)`: `d ~ U{1..max}`; `DelayDist.exponential(max, rate)`:
/// `p(d = k) ∝ exp(−rate·k)` over `{0..max}`.
#[pyclass(module = "pir2._pir2", name = "DelayDist", frozen, eq)]
#[derive(Debug, Clone, PartialEq)]
struct PyDelayDist {
    inner: DelayDist,
}

#[pymethods]
impl PyDelayDist {
    /// Uniform over `{1, …, max}` (`max >= 1`).
    #[staticmethod]
    fn uniform(max: i64) -> PyResult<Self> {
        let d = DelayDist::Uniform {
            max: count("delay.max", max)?,
        };
        d.validate().map_err(err)?;
        Ok(Self { inner: d })
    }

    /// `p(k) ∝ exp(−rate·k)` over `{0, …, max}` (`rate` finite and `>= 0`).
    #[staticmethod]
    fn exponential(max: i64, rate: f64) -> PyResult<Self> {
        let d = DelayDist::Exponential {
            max: count("delay.max", max)?,
            rate,
        };
        d.validate().map_err(err)?;
        Ok(Self { inner: d })
    }

    /// `"uniform"` or `"exponential"`.
    #[getter]
    fn kind(&self) -> &'static str {
        match self.inner {
            DelayDist::Uniform { .. } => "uniform",
            DelayDist::Exponential { .. } => "exponential",
        }
    }

    /// The largest delay this distribution can produce.
    #[getter]
    fn max(&self) -> usize {
        self.inner.max()
    }

    /// The decay rate of an exponential law (`None` for the uniform law).
    #[getter]
    fn rate(&self) -> Option<f64> {
        match self.inner {
            DelayDist::Uniform { .. } => None,
            DelayDist::Exponential { rate, .. } => Some(rate),
        }
    }

    /// Probability of delay `k`.
    fn pmf(&self, k: i64) -> PyResult<f64> {
        Ok(self.inner.pmf(count("k", k)?))
    }

    /// Sample delays with `rng` (a `pir2.Rng`, advanced in place, or an integer seed): one
    /// `int`, or an `int64` array of `size` draws.
    #[pyo3(signature = (rng, size=None))]
    fn sample(
        &self,
        py: Python<'_>,
        rng: &Bound<'_, PyAny>,
        size: Option<i64>,
    ) -> PyResult<Py<PyAny>> {
        let size = opt_count("size", size)?;
        with_rng(rng, |r| match size {
            None => Ok(self.inner.sample(r).into_pyobject(py)?.into_any().unbind()),
            Some(n) => {
                let v: Vec<i64> = (0..n).map(|_| self.inner.sample(r) as i64).collect();
                Ok(arr1(py, v).into_any().unbind())
            }
        })
    }

    fn __repr__(&self) -> String {
        match self.inner {
            DelayDist::Uniform { max } => format!("DelayDist.uniform({max})"),
            DelayDist::Exponential { max, rate } => {
                format!("DelayDist.exponential({max}, {rate:?})")
            }
        }
    }
}

/// A batch of training draws: per sample the true noise level per position, the loss mask,
/// the drawn delay and whether the front is hidden from the model.
///
/// Attributes (numpy arrays, `B` samples of chunk length `H`): `tau` `float32 [B, H]`,
/// `mask` `float32 [B, H]` (0 on the front), `delay` `int64 [B]` (0 for unmasked draws),
/// `hidden` `bool [B]`.
#[pyclass(module = "pir2._pir2", name = "Draws", frozen)]
#[derive(Debug)]
struct PyDraws {
    draws: Vec<Draw>,
    horizon: usize,
    /// True noise level per position, `float32 [B, H]`.
    #[pyo3(get)]
    tau: Py<PyArray2<f32>>,
    /// Loss mask per position, `float32 [B, H]` (0 on the front).
    #[pyo3(get)]
    mask: Py<PyArray2<f32>>,
    /// The drawn delay (front length) per sample, `int64 [B]`; 0 for unmasked draws.
    #[pyo3(get)]
    delay: Py<PyArray1<i64>>,
    /// Whether the front is hidden from the model, `bool [B]`.
    #[pyo3(get)]
    hidden: Py<PyArray1<bool>>,
}

impl PyDraws {
    fn from_draws(py: Python<'_>, draws: Vec<Draw>, horizon: usize) -> PyResult<Self> {
        let b = draws.len();
        let mut tau = Vec::with_capacity(b * horizon);
        let mut mask = Vec::with_capacity(b * horizon);
        for d in &draws {
            tau.extend_from_slice(&d.tau);
            mask.extend_from_slice(&d.mask);
        }
        let delay: Vec<i64> = draws.iter().map(|d| d.delay as i64).collect();
        let hidden: Vec<bool> = draws.iter().map(|d| d.hidden).collect();
        Ok(Self {
            tau: arr2(py, tau, b, horizon)?.unbind(),
            mask: arr2(py, mask, b, horizon)?.unbind(),
            delay: arr1(py, delay).unbind(),
            hidden: arr1(py, hidden).unbind(),
            draws,
            horizon,
        })
    }
}

#[pymethods]
impl PyDraws {
    /// Chunk length `H`.
    #[getter]
    fn horizon(&self) -> usize {
        self.horizon
    }

    /// Build the model input and the regression target from ground-truth `actions` and
    /// noise `eps` (both `[B, H, A]`), per sample as Rust `Draw::build`:
    /// `x = (1−τ)·ε + τ·a` (front zeroed if hidden), `tau_in = τ` (or `HIDDEN_FRONT_TAU` on
    /// a hidden front), `target = a − ε`. Returns `(x [B,H,A], tau_in [B,H], target [B,H,A])`
    /// as `float32` arrays.
    fn build<'py>(
        &self,
        py: Python<'py>,
        actions: &Bound<'py, PyAny>,
        eps: &Bound<'py, PyAny>,
    ) -> PyResult<(Py<PyAny>, Py<PyAny>, Py<PyAny>)> {
        let (b, h) = (self.draws.len(), self.horizon);
        let (act, shape) = f32_any(py, actions)?;
        if shape.len() != 3 || shape[0] != b || shape[1] != h {
            return Err(invalid(
                "actions",
                format!("has shape {shape:?}, expected [B, H, A] = [{b}, {h}, A]"),
            ));
        }
        let a = shape[2];
        let eps = f32_input(py, eps, "eps", &shape)?;
        let n = h * a;
        let mut x = vec![0.0f32; b * n];
        let mut tau_in = vec![0.0f32; b * h];
        let mut target = vec![0.0f32; b * n];
        for (i, d) in self.draws.iter().enumerate() {
            let r = i * n..(i + 1) * n;
            d.build(
                &act[r.clone()],
                &eps[r.clone()],
                a,
                &mut x[r.clone()],
                &mut tau_in[i * h..(i + 1) * h],
                &mut target[r],
            )
            .map_err(err)?;
        }
        let to3 = |v: Vec<f32>| -> PyResult<Py<PyAny>> {
            Array3::from_shape_vec((b, h, a), v)
                .map(|arr| arr.into_pyarray(py).into_any().unbind())
                .map_err(|e| PyValueError::new_err(e.to_string()))
        };
        Ok((
            to3(x)?,
            arr2(py, tau_in, b, h)?.into_any().unbind(),
            to3(target)?,
        ))
    }

    fn __len__(&self) -> usize {
        self.draws.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "Draws(batch={}, horizon={})",
            self.draws.len(),
            self.horizon
        )
    }
}

/// A training schedule: the per-sample `τ` / mask / delay recipe of one policy family
/// (Rust `pir2_schedule::train::TrainSchedule`).
///
/// Constructors mirror the Rust variants: `TrainSchedule.pi_r2(...)` (πR²: warm-up branch
/// or staircase branch; with `front="hidden"` the front-hidden policy, with `n=None,
/// alignment="paper"` the paper's full ramp), `train_time_rtc(delay)`, `standard_flow()`,
/// `gr00t_flow()` (shared `τ` from GR00T N1.7's Beta law), `streaming_diffusion()`;
/// `for_policy(name, recipe)` gives the schedule pir2's trainer uses for a named policy.
/// `draw(batch, horizon, rng)` draws a batch exactly as `batch` successive Rust
/// `TrainSchedule::draw` calls on one generator.
#[pyclass(module = "pir2._pir2", name = "TrainSchedule", frozen, eq)]
#[derive(Debug, Clone, PartialEq)]
struct PyTrainSchedule {
    inner: TrainSchedule,
}

#[pymethods]
impl PyTrainSchedule {
    /// πR² draws (Rust `PiR2Draws`; defaults are Rust's `PiR2Draws::default()`).
    ///
    /// - `alpha`: probability of the warm-up branch (one shared `τ ~ U[0,1]`, no mask);
    /// - `delay`: `DelayDist` of the staircase branch (default `DelayDist.uniform(5)`);
    /// - `n`: NFEs per action (`None` = full ramp), capped at `n_max(H, d)` per draw;
    /// - `alignment`: `"fresh"` or `"paper"`;
    /// - `jitter`: half-width of the symmetric `τ` jitter on non-front positions;
    /// - `front`: `"visible"`, `"hidden"` (front zeroed, `τ = HIDDEN_FRONT_TAU` for the
    ///   model) or `"dropped"` (hidden with probability `front_p` per draw).
    #[staticmethod]
    #[pyo3(signature = (alpha=0.2, delay=None, n=None, alignment="fresh", jitter=0.0, front="visible", front_p=None))]
    fn pi_r2(
        alpha: f32,
        delay: Option<PyDelayDist>,
        n: Option<i64>,
        alignment: &str,
        jitter: f32,
        front: &str,
        front_p: Option<f32>,
    ) -> PyResult<Self> {
        let front = match (front, front_p) {
            ("visible", None) => FrontVisibility::Visible,
            ("hidden", None) => FrontVisibility::Hidden,
            ("dropped", Some(p)) => FrontVisibility::Dropped { p },
            ("dropped", None) => {
                return Err(invalid(
                    "front.p",
                    "front=\"dropped\" needs front_p in [0,1]",
                ))
            }
            ("visible" | "hidden", Some(_)) => {
                return Err(invalid(
                    "front.p",
                    "front_p is only used with front=\"dropped\"",
                ))
            }
            (other, _) => {
                return Err(invalid(
                    "front",
                    format!("must be \"visible\", \"hidden\" or \"dropped\", got {other:?}"),
                ))
            }
        };
        let base = PiR2Draws::default();
        let c = PiR2Draws {
            alpha,
            delay: delay.map(|d| d.inner).unwrap_or(base.delay),
            n: opt_count("n", n)?,
            alignment: alignment_arg(alignment)?,
            jitter,
            front,
        };
        // Horizon-free checks now (the staircase checks need H: `validate(H)` / `draw`).
        let s = TrainSchedule::PiR2(c);
        if let Err(e) = s.validate(usize::MAX / 4) {
            if !matches!(
                e,
                Error::HorizonTooShort { .. } | Error::NfeOutOfRange { .. }
            ) {
                return Err(err(e));
            }
        }
        Ok(Self { inner: s })
    }

    /// Train-time RTC: clean front of `d ~ delay`, one shared `τ ~ U[0,1]` on the back
    /// (default delay `DelayDist.uniform(10)`, the paper's `d_max`).
    #[staticmethod]
    #[pyo3(signature = (delay=None))]
    fn train_time_rtc(delay: Option<PyDelayDist>) -> PyResult<Self> {
        let delay = delay
            .map(|d| d.inner)
            .unwrap_or(DelayDist::Uniform { max: 10 });
        delay.validate().map_err(err)?;
        Ok(Self {
            inner: TrainSchedule::TrainTimeRtc { delay },
        })
    }

    /// Standard flow matching: one shared `τ ~ U[0,1]`, no mask.
    #[staticmethod]
    fn standard_flow() -> Self {
        Self {
            inner: TrainSchedule::StandardFlow,
        }
    }

    /// Standard flow matching with GR00T N1.7's law of the shared `τ`
    /// (`τ = 0.999·(1 − B)`, `B ~ Beta(1.5, 1)`), no mask.
    #[staticmethod]
    fn gr00t_flow() -> Self {
        Self {
            inner: TrainSchedule::Gr00tFlow,
        }
    }

    /// Streaming diffusion: ramp `τ_p = 1 − (p + u)/H`, `u ~ U[0,1)`, no mask.
    #[staticmethod]
    fn streaming_diffusion() -> Self {
        Self {
            inner: TrainSchedule::StreamingDiffusion,
        }
    }

    /// The schedule pir2 trains a named policy with (Rust `Policy::schedule`): `policy` is
    /// one of `"pi_r2"`, `"pi_r2_hidden"`, `"pi_r2_full"`, `"rtc"`, `"flow"`,
    /// `"pi_r2_zero_delay"`, `"pi_r2_zero_delay_full"`; `recipe` is `"default"`,
    /// `"paper_sim"` or a dict of Rust `Recipe` fields overriding the default (e.g.
    /// `{"nfe": 2, "pir2_d_max": 5, "delays": {"law": "exponential", "rate": 1.0}}`).
    #[staticmethod]
    #[pyo3(signature = (policy, recipe=None))]
    fn for_policy(
        py: Python<'_>,
        policy: &str,
        recipe: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let p: Policy = serde_json::from_value(serde_json::Value::String(policy.into()))
            .map_err(|_| {
                invalid(
                    "policy",
                    format!(
                        "unknown policy {policy:?}; expected one of pi_r2, pi_r2_hidden, pi_r2_full, rtc, flow, pi_r2_zero_delay, pi_r2_zero_delay_full"
                    ),
                )
            })?;
        let r =
            match recipe {
                None => Recipe::default(),
                Some(obj) if obj.is_none() => Recipe::default(),
                Some(obj) => {
                    if let Ok(name) = obj.extract::<String>() {
                        match name.as_str() {
                            "default" => Recipe::default(),
                            "paper_sim" => Recipe::paper_sim(),
                            _ => return Err(invalid(
                                "recipe",
                                format!(
                                    "must be \"default\", \"paper_sim\" or a dict, got {name:?}"
                                ),
                            )),
                        }
                    } else if obj.is_instance_of::<PyDict>() {
                        let text: String = py
                            .import("json")?
                            .call_method1("dumps", (obj,))?
                            .extract()?;
                        let given: serde_json::Value = serde_json::from_str(&text)
                            .map_err(|e| invalid("recipe", e.to_string()))?;
                        check_recipe_keys(&given)?;
                        serde_json::from_value(given)
                            .map_err(|e| invalid("recipe", e.to_string()))?
                    } else {
                        return Err(invalid(
                            "recipe",
                            "must be \"default\", \"paper_sim\" or a dict",
                        ));
                    }
                }
            };
        Ok(Self {
            inner: p.schedule(&r),
        })
    }

    /// Rebuild a schedule from its JSON form (the serde form pir2's configs use, e.g.
    /// `{"kind": "pi_r2", "alpha": 0.2, "n": 2}`).
    #[staticmethod]
    fn from_json(text: &str) -> PyResult<Self> {
        let s: TrainSchedule =
            serde_json::from_str(text).map_err(|e| invalid("schedule", e.to_string()))?;
        Ok(Self { inner: s })
    }

    /// The JSON form of this schedule (serde, as in pir2's configs).
    fn to_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.inner).map_err(|e| invalid("schedule", e.to_string()))
    }

    /// The variant: `"pi_r2"`, `"train_time_rtc"`, `"standard_flow"`, `"gr00t_flow"` or
    /// `"streaming_diffusion"`.
    #[getter]
    fn kind(&self) -> &'static str {
        match self.inner {
            TrainSchedule::PiR2(_) => "pi_r2",
            TrainSchedule::TrainTimeRtc { .. } => "train_time_rtc",
            TrainSchedule::StandardFlow => "standard_flow",
            TrainSchedule::Gr00tFlow => "gr00t_flow",
            TrainSchedule::StreamingDiffusion => "streaming_diffusion",
        }
    }

    /// Validate the schedule for chunk length `horizon` (every delay it can draw must give
    /// a valid staircase); raises `ValueError` with the Rust error's text.
    fn validate(&self, horizon: i64) -> PyResult<()> {
        self.inner.validate(count("H", horizon)?).map_err(err)
    }

    /// Draw `batch` samples for chunk length `horizon`: `batch` successive Rust
    /// `TrainSchedule::draw` calls on one generator. `rng` is a `pir2.Rng` (advanced in
    /// place: the next call continues the stream) or an integer seed (a fresh
    /// `Rng(seed)`). The schedule is validated for `horizon` first. Returns `Draws`.
    fn draw(
        &self,
        py: Python<'_>,
        batch: i64,
        horizon: i64,
        rng: &Bound<'_, PyAny>,
    ) -> PyResult<PyDraws> {
        let b = count("batch", batch)?;
        let h = count("H", horizon)?;
        b.checked_mul(h)
            .filter(|&n| n <= isize::MAX as usize / 8)
            .ok_or_else(|| invalid("batch", format!("batch × H = {b} × {h} is too large")))?;
        self.inner.validate(h).map_err(err)?;
        let draws = with_rng(rng, |r| {
            let mut out = Vec::with_capacity(b);
            for _ in 0..b {
                let mut d = Draw::new(h);
                self.inner.draw(r, &mut d).map_err(err)?;
                out.push(d);
            }
            Ok(out)
        })?;
        PyDraws::from_draws(py, draws, h)
    }

    fn __repr__(&self) -> String {
        format!(
            "TrainSchedule.from_json({:?})",
            serde_json::to_string(&self.inner).unwrap_or_default()
        )
    }
}

// ---------------------------------------------------------------------------------------
// StreamBuffer
// ---------------------------------------------------------------------------------------

/// What a call produced: slots `[start, start + len)` are clean and are the actions to
/// execute after the in-flight front (Rust `Emitted`). Unpacks as `start, len = e`.
#[pyclass(module = "pir2._pir2", name = "Emitted", frozen, eq)]
#[derive(Debug, Clone, PartialEq)]
struct PyEmitted {
    /// First emitted slot (= the call's delay `d`).
    #[pyo3(get)]
    start: usize,
    /// Number of emitted slots (`max(d, 1)`).
    #[pyo3(get)]
    len: usize,
}

#[pymethods]
impl PyEmitted {
    fn __iter__(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        let t = (self.start, self.len).into_pyobject(py)?;
        Ok(t.call_method0("__iter__")?.unbind())
    }

    fn __repr__(&self) -> String {
        format!("Emitted(start={}, len={})", self.start, self.len)
    }
}

/// Error of `warm_start_with`: the schedule's or the Python model's.
enum WarmError {
    Schedule(Error),
    Python(PyErr),
}

impl From<Error> for WarmError {
    fn from(e: Error) -> Self {
        WarmError::Schedule(e)
    }
}

/// The streaming inference buffer (Rust `pir2_schedule::StreamBuffer`): one denoising step
/// per call, `d` clean actions out.
///
/// A call at delay `d`: `plan(d)` (commit the front, compute `Δτ`), evaluate your model's
/// velocity on `model_x` / `model_tau`, `step(v)` (Euler step; returns the emitted slots),
/// and after executing `k` slots `slide(k)` (shift left, append fresh noise). The fresh
/// noise comes from the buffer's own generator seeded by `seed`: same seed, same bits as
/// Rust. Arrays returned are copies (`float32`; chunks `[H, A]`, noise levels `[H]`).
#[pyclass(module = "pir2._pir2", name = "StreamBuffer")]
#[derive(Debug, Clone)]
struct PyStreamBuffer {
    inner: StreamBuffer,
}

impl PyStreamBuffer {
    fn ha(&self) -> (usize, usize) {
        let c = self.inner.config();
        (c.horizon, c.action_dim)
    }

    fn chunk<'py>(&self, py: Python<'py>, v: &[f32]) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (h, a) = self.ha();
        arr2(py, v.to_vec(), h, a)
    }

    fn slot_index(&self, p: i64) -> PyResult<usize> {
        let h = self.ha().0;
        let p = count("p", p)?;
        if p >= h {
            return Err(invalid(
                "p",
                format!("slot {p} is out of range for H = {h}"),
            ));
        }
        Ok(p)
    }
}

#[pymethods]
impl PyStreamBuffer {
    /// A buffer of pure noise (`τ = 0` everywhere), Rust `StreamBuffer::new(StreamConfig
    /// {..}, seed)`; defaults are Rust's `StreamConfig::default()`. Every `d <= max_delay`
    /// must give a valid staircase; `seed` (default 0) seeds the buffer's noise. Call
    /// `warm_start` (or `warm_start_with`) first.
    #[new]
    #[pyo3(signature = (horizon=16, action_dim=1, nfe=None, alignment="fresh", front="visible", max_delay=5, seed=None))]
    fn new(
        horizon: i64,
        action_dim: i64,
        nfe: Option<i64>,
        alignment: &str,
        front: &str,
        max_delay: i64,
        seed: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let cfg = StreamConfig {
            horizon: count("horizon", horizon)?,
            action_dim: count("action_dim", action_dim)?,
            nfe: opt_count("nfe", nfe)?,
            alignment: alignment_arg(alignment)?,
            front: front_mode_arg(front)?,
            max_delay: count("max_delay", max_delay)?,
        };
        let seed = seed.map(seed_arg).transpose()?.unwrap_or(0);
        let inner = StreamBuffer::new(cfg, seed).map_err(err)?;
        Ok(Self { inner })
    }

    /// The configuration as a dict (`horizon`, `action_dim`, `nfe`, `alignment`, `front`,
    /// `max_delay`).
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let c = self.inner.config();
        let d = PyDict::new(py);
        d.set_item("horizon", c.horizon)?;
        d.set_item("action_dim", c.action_dim)?;
        d.set_item("nfe", c.nfe)?;
        d.set_item("alignment", c.alignment.name())?;
        d.set_item("front", front_mode_name(c.front))?;
        d.set_item("max_delay", c.max_delay)?;
        Ok(d)
    }

    /// Chunk length `H`.
    #[getter]
    fn horizon(&self) -> usize {
        self.ha().0
    }

    /// Action dimension `A`.
    #[getter]
    fn action_dim(&self) -> usize {
        self.ha().1
    }

    /// The staircase this buffer uses at delay `d` (with `n` capped at `n_max(H, d)`).
    fn staircase(&self, d: i64) -> PyResult<PyStaircase> {
        let s = self.inner.staircase(count("d", d)?).map_err(err)?;
        Ok(PyStaircase { inner: s })
    }

    /// The chunk `x`, `float32 [H, A]`.
    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.chunk(py, self.inner.x())
    }

    /// Noise levels `τ`, `float32 [H]`.
    #[getter]
    fn tau<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        arr1(py, self.inner.tau().to_vec())
    }

    /// Clean estimates `x̂ = x + (1−τ)·v` from the last call, `float32 [H, A]`.
    #[getter]
    fn xhat<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.chunk(py, self.inner.xhat())
    }

    /// `Δτ` planned for the current call (zero outside a call), `float32 [H]`.
    #[getter]
    fn delta<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        arr1(py, self.inner.delta().to_vec())
    }

    /// The chunk the model sees this call (front zeroed if hidden), `float32 [H, A]`.
    #[getter]
    fn model_x<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.chunk(py, self.inner.model_x())
    }

    /// The `τ` the model sees this call (`HIDDEN_FRONT_TAU` on a hidden front), `[H]`.
    #[getter]
    fn model_tau<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        arr1(py, self.inner.model_tau().to_vec())
    }

    /// Slot `p` of `x`, `float32 [A]`.
    fn slot<'py>(&self, py: Python<'py>, p: i64) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let p = self.slot_index(p)?;
        Ok(arr1(py, self.inner.slot(p).to_vec()))
    }

    /// Slot `p` of `x̂`, `float32 [A]`.
    fn xhat_slot<'py>(&self, py: Python<'py>, p: i64) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let p = self.slot_index(p)?;
        Ok(arr1(py, self.inner.xhat_slot(p).to_vec()))
    }

    /// Absolute index (count of slots slid out so far) of slot 0.
    #[getter]
    fn index(&self) -> u64 {
        self.inner.index()
    }

    /// Number of leading clean slots (`τ = 1`).
    #[getter]
    fn clean_prefix(&self) -> usize {
        self.inner.clean_prefix()
    }

    /// Re-noise a clean chunk (`[H, A]`) to the staircase at delay `d0` with fresh noise;
    /// `x̂` becomes `clean`.
    fn warm_start(&mut self, py: Python<'_>, d0: i64, clean: &Bound<'_, PyAny>) -> PyResult<()> {
        let (h, a) = self.ha();
        let clean = f32_input(py, clean, "clean chunk", &[h, a])?;
        self.inner.warm_start(count("d", d0)?, &clean).map_err(err)
    }

    /// Warm start with `k`-step standard flow from pure noise, then re-noise to the
    /// staircase at `d0`. `model(x, tau)` takes `x` `float32 [H, A]` and `tau` `float32 [H]`
    /// and returns the velocity `[H, A]`; an exception it raises is re-raised.
    fn warm_start_with(
        &mut self,
        py: Python<'_>,
        d0: i64,
        k: i64,
        model: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let (h, a) = self.ha();
        let d0 = count("d", d0)?;
        let k = count("k", k)?;
        let r = self
            .inner
            .warm_start_with(d0, k, |x: &[f32], tau: &[f32], v: &mut [f32]| {
                let xa = arr2(py, x.to_vec(), h, a).map_err(WarmError::Python)?;
                let ta = arr1(py, tau.to_vec());
                let out = model.call1((xa, ta)).map_err(WarmError::Python)?;
                let got = f32_input(py, &out, "velocity", &[h, a]).map_err(WarmError::Python)?;
                v.copy_from_slice(&got);
                Ok::<(), WarmError>(())
            });
        match r {
            Ok(()) => Ok(()),
            Err(WarmError::Schedule(e)) => Err(err(e)),
            Err(WarmError::Python(e)) => Err(e),
        }
    }

    /// Plan a call at delay `d`: commit the front, compute `Δτ`.
    fn plan(&mut self, d: i64) -> PyResult<()> {
        self.inner.plan(count("d", d)?).map_err(err)
    }

    /// Apply the Euler step with the model's velocity `v` (`[H, A]`), update `x̂`; returns
    /// the emitted slots. A non-finite velocity is rejected before anything changes.
    fn step(&mut self, py: Python<'_>, v: &Bound<'_, PyAny>) -> PyResult<PyEmitted> {
        let (h, a) = self.ha();
        let v = f32_input(py, v, "velocity", &[h, a])?;
        let e = self.inner.step(&v).map_err(err)?;
        Ok(PyEmitted {
            start: e.start,
            len: e.len,
        })
    }

    /// Change the action coordinates of every slot, keeping each slot's noise: `xhat_new`
    /// (`[H, A]`) is every slot's clean estimate in the new coordinates (Rust
    /// `StreamBuffer::remap` with the map `p ↦ xhat_new[p]`). Clean slots become exactly
    /// `xhat_new`; a partly denoised slot moves by `τ·(xhat_new − x̂)`; values equal bit for
    /// bit to the current `x̂` are not touched. Drops a pending plan.
    fn remap(&mut self, py: Python<'_>, xhat_new: &Bound<'_, PyAny>) -> PyResult<()> {
        let (h, a) = self.ha();
        let z = f32_input(py, xhat_new, "xhat_new", &[h, a])?;
        self.inner
            .remap(|p, _, out| out.copy_from_slice(&z[p * a..(p + 1) * a]));
        Ok(())
    }

    /// Slide left by `k` executed slots and append `k` fresh-noise slots (`τ = 0`).
    fn slide(&mut self, k: i64) -> PyResult<()> {
        self.inner.slide(count("k", k)?).map_err(err)
    }

    fn __repr__(&self) -> String {
        let c = self.inner.config();
        format!(
            "StreamBuffer(horizon={}, action_dim={}, nfe={}, alignment={:?}, front={:?}, max_delay={}, index={})",
            c.horizon,
            c.action_dim,
            c.nfe.map_or("None".to_string(), |n| n.to_string()),
            c.alignment.name(),
            front_mode_name(c.front),
            c.max_delay,
            self.inner.index()
        )
    }
}

// ---------------------------------------------------------------------------------------
// LatencyWindow
// ---------------------------------------------------------------------------------------

/// The runtime's rolling latency window that measures the delay `d` (Rust
/// `pir2_runtime::LatencyWindow`): `d = max(1, round(mean / period))`, clamped to `d_max`.
///
/// The first `warmup` pushes are not recorded. As in Rust, `w` and `d_max` below 1 are
/// raised to 1 and a `period_ns` of 0 to 1 ns. Latencies are integer nanoseconds.
#[pyclass(module = "pir2._pir2", name = "LatencyWindow")]
#[derive(Debug, Clone)]
struct PyLatencyWindow {
    inner: LatencyWindow,
}

#[pymethods]
impl PyLatencyWindow {
    /// Window of `w` calls, skipping the first `warmup` pushes, control period
    /// `period_ns` nanoseconds, clamp at `d_max`; `initial_delay` is reported before
    /// anything is recorded (default 1, clamped to `[1, d_max]`).
    #[new]
    #[pyo3(signature = (w, warmup, period_ns, d_max, initial_delay=None))]
    fn new(
        w: i64,
        warmup: i64,
        period_ns: i64,
        d_max: i64,
        initial_delay: Option<i64>,
    ) -> PyResult<Self> {
        let mut inner = LatencyWindow::new(
            count("w", w)?,
            count("warmup", warmup)?,
            count("period_ns", period_ns)? as u64,
            count("d_max", d_max)?,
        );
        if let Some(d) = opt_count("initial_delay", initial_delay)? {
            inner = inner.with_initial_delay(d);
        }
        Ok(Self { inner })
    }

    /// Record one call latency (nanoseconds, `>= 0`), or every value of an integer array
    /// in order.
    fn push(&mut self, py: Python<'_>, latency_ns: &Bound<'_, PyAny>) -> PyResult<()> {
        if let Ok(v) = latency_ns.extract::<i64>() {
            self.inner.push(count("latency_ns", v)? as u64);
            return Ok(());
        }
        let np = py.import("numpy")?;
        let a = np.call_method1("asarray", (latency_ns,))?;
        let kind: String = a.getattr("dtype")?.getattr("kind")?.extract()?;
        if kind != "i" && kind != "u" {
            return Err(invalid(
                "latency_ns",
                format!("must be integer nanoseconds, got dtype kind {kind:?}"),
            ));
        }
        let a = np.call_method1("ascontiguousarray", (a, "int64"))?;
        let a: PyReadonlyArrayDyn<'_, i64> = a.extract()?;
        let v = a.as_slice()?;
        if let Some(bad) = v.iter().find(|&&x| x < 0) {
            return Err(invalid("latency_ns", format!("must be >= 0, got {bad}")));
        }
        for &x in v {
            self.inner.push(x as u64);
        }
        Ok(())
    }

    /// Mean latency over the window in nanoseconds, or `None` if nothing is recorded.
    #[getter]
    fn mean(&self) -> Option<f64> {
        self.inner.mean()
    }

    /// The delay `d = max(1, round(mean / period))`, clamped to `d_max`.
    #[getter]
    fn delay(&self) -> usize {
        self.inner.delay()
    }

    /// True when nothing is recorded yet.
    fn is_empty(&self) -> bool {
        self.inner.is_empty()
    }

    /// Number of recorded latencies.
    fn __len__(&self) -> usize {
        self.inner.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "LatencyWindow(len={}, mean={}, delay={})",
            self.inner.len(),
            self.inner
                .mean()
                .map_or("None".to_string(), |m| format!("{m:?}")),
            self.inner.delay()
        )
    }
}

// ---------------------------------------------------------------------------------------

/// pir2's Rust core (`pir2._pir2`); import `pir2` instead.
#[pymodule]
fn _pir2(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyRng>()?;
    m.add_class::<PyStaircase>()?;
    m.add_class::<PyDelayDist>()?;
    m.add_class::<PyTrainSchedule>()?;
    m.add_class::<PyDraws>()?;
    m.add_class::<PyStreamBuffer>()?;
    m.add_class::<PyEmitted>()?;
    m.add_class::<PyLatencyWindow>()?;
    m.add_function(wrap_pyfunction!(staircase, m)?)?;
    m.add_function(wrap_pyfunction!(gr00t_n17_tau, m)?)?;
    m.add_function(wrap_pyfunction!(gr00t_n17_tau_cdf, m)?)?;
    m.add("HIDDEN_FRONT_TAU", pir2_schedule::HIDDEN_FRONT_TAU)?;
    m.add("GR00T_N17_TAU_ALPHA", train::GR00T_N17_TAU_ALPHA)?;
    m.add("GR00T_N17_TAU_BETA", train::GR00T_N17_TAU_BETA)?;
    m.add("GR00T_N17_TAU_SCALE", train::GR00T_N17_TAU_SCALE)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
