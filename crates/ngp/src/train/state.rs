//! A trainer's whole state between two steps, as bytes: what a run killed at step 49 000
//! needs to go on exactly where it stopped. Restored into a trainer built from the same
//! scenes and options, the next steps are the ones the uninterrupted run would have taken,
//! bit for bit (on the CPU, with the same worker count: the gradient partitions are summed
//! in a fixed order). The GPU trainer writes the same document with `device: gpu` in its
//! fingerprint and what it keeps on the device; a state goes back only into its own kind of
//! trainer, and on the GPU the next steps are the same steps, not bit for bit (its float
//! sums depend on the order its threads add in).
//!
//! The document is msgpack: `format`, `version`, a `fingerprint` of what must not change
//! (layout, scenes, options, workers), then the weights, the optimizer's moments and EMA,
//! the occupancy-update clock and every scene's grid and batch counters, arrays as
//! little-endian binaries. Every length is checked against the trainer before anything is
//! copied, so a damaged or forged file is an error naming the field.
//!
//! Both trainers write and read the document through one type, [`TrainerState`] (one
//! writer, [`TrainerState::to_value`]; one reader, [`TrainerState::read`]); each only
//! converts between its own storage and it. What differs by device is a field of it.

use super::cameras::RefinerState;
use crate::error::{Error, Result};
use crate::snapshot::msgpack;
/// The document's values (what a backend's [`super::TrainBackend::save_state`] returns).
pub use rmpv::Value;
use std::borrow::Cow;
use std::path::Path;

pub const FORMAT: &str = "stegongp-train-state";
/// 2: a training policy's state, the mechanisms' (held-back gradients, table bounds) and
/// the gradients a step left waiting in the workers' buffers.
pub const VERSION: u64 = 2;
/// The fingerprint entry naming the kind of trainer that saved a state; a state without it
/// is the CPU trainer's.
pub const DEVICE: &str = "device";
/// The fingerprint's key of camera refinement's settings, present only where a run refines.
pub const CAMERAS: &str = "cameras";

pub fn f32s(v: &[f32]) -> Value {
    u32s(bytemuck::cast_slice(v))
}

pub fn u32s(v: &[u32]) -> Value {
    // Sized once and filled in place: a collected flat_map grows its buffer step by step.
    let mut out = vec![0u8; v.len() * 4];
    for (o, x) in out.chunks_exact_mut(4).zip(v) {
        o.copy_from_slice(&x.to_le_bytes());
    }
    Value::Binary(out)
}

/// Bit sets (64 members a word), little-endian.
pub fn u64s(v: &[u64]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

/// Removes `key` from a map and returns its value (a document split to be nested
/// elsewhere: a checkpoint's optimizer, an experiment's run state).
pub fn take(doc: &mut Value, key: &str) -> Option<Value> {
    let Value::Map(m) = doc else {
        return None;
    };
    let i = m.iter().position(|(k, _)| k.as_str() == Some(key))?;
    Some(m.remove(i).1)
}

/// Sets `key` of a map (added at the end when absent).
pub fn put(doc: &mut Value, key: &str, value: Value) {
    if let Value::Map(m) = doc {
        match m.iter_mut().find(|(k, _)| k.as_str() == Some(key)) {
            Some((_, v)) => *v = value,
            None => m.push((Value::from(key), value)),
        }
    }
}

pub fn map(entries: Vec<(&str, Value)>) -> Value {
    Value::Map(
        entries
            .into_iter()
            .map(|(k, v)| (Value::String(k.into()), v))
            .collect(),
    )
}

pub fn encode(v: &Value) -> Vec<u8> {
    let mut out = Vec::with_capacity(msgpack::binary_bytes(v) + (1 << 16));
    msgpack::encode(v, &mut out);
    out
}

/// A trainer's whole state between two steps, as the document holds it: what both
/// trainers write ([`Self::to_value`]) and read back ([`Self::read`]), each converting
/// between its own storage (host vectors; device buffers read back or uploaded) and this.
/// Large arrays a trainer keeps on the host are borrowed to save them; read back, every
/// field is owned, or borrowed from the document. Where the two kinds of trainer keep
/// different things, the field says so: [`OptimizerState::ema_step`],
/// [`Self::occupancy_clock`], [`Scene::march_stride`], [`Self::mechanisms`] and
/// [`Waiting`] (and the fingerprint's [`DEVICE`] entry).
pub struct TrainerState<'a> {
    /// [`fingerprint`]: what must not change between the run that saved the state and the
    /// one that goes on (read back: the trainer's own, which the saved one matched).
    pub fingerprint: Vec<(String, String)>,
    /// Steps taken, updating the weights or not.
    pub step: u32,
    /// Steps that updated the weights: the optimizer's step count.
    pub weight_steps: u32,
    /// The training weights.
    pub params: Cow<'a, [f32]>,
    pub optimizer: OptimizerState<'a>,
    /// The occupancy updates' clock ([`super::GridUpdates::clock`]): the CPU's; `None` on
    /// the GPU, whose document has no such field (its update schedule is a function of
    /// `weight_steps` alone).
    pub occupancy_clock: Option<OccupancyClock<'a>>,
    /// Every scene's occupancy grid and batch counters, in the trainer's order.
    pub scenes: Vec<Scene<'a>>,
    /// The policy mechanisms' state. The CPU always writes it (each part absent until a
    /// policy first used it); the GPU only with a policy installed (`None`: nil).
    pub mechanisms: Option<Mechanisms<'a>>,
    /// The gradients a step that did not update the weights left waiting.
    pub waiting: Waiting<'a>,
    /// The training policy's own state (`None`: nil, no policy or one that keeps none).
    pub policy: Option<Cow<'a, [u8]>>,
    /// Scene 0's camera refinement ([`super::cameras`]), where it refines; a state without
    /// refinement has no such field.
    pub cameras: Option<RefinerState>,
}

/// Where the gradients a step left waiting are kept, by kind of trainer.
pub enum Waiting<'a> {
    /// The CPU's: each worker's gradient buffer and the groups it touched (`workers`).
    Workers(Vec<Worker<'a>>),
    /// The GPU's one gradient buffer (`gradient`), saved only with a policy installed
    /// (`None`: nil; without a policy the buffer is zero after every step).
    Gradient(Option<Sparse>),
}

/// One CPU worker's gradient buffer and the [`super::optimizer::GROUP`]s it touched.
pub struct Worker<'a> {
    pub grad: Sparse,
    pub touched: Cow<'a, [u64]>,
}

/// The occupancy-update clock: per scene, the weight steps since its last update, and the
/// updates made.
pub struct OccupancyClock<'a> {
    pub since: Cow<'a, [u64]>,
    pub updates: u32,
}

/// One scene's part of a trainer's state: its occupancy grid and the batch counters
/// (rays per batch, trained and marched samples of its last step).
pub struct Scene<'a> {
    pub grid: Cow<'a, crate::occupancy::OccupancyGrid>,
    pub rays_per_batch: u32,
    pub measured_samples: u32,
    pub measured_marched: u32,
    /// The coarse march's stride ([`super::coarse`]); always 1 on the GPU, which marches
    /// the reference's step (and refuses any other).
    pub march_stride: u32,
}

/// The policy mechanisms' state; each part `None` (nil) until a policy first used it.
pub struct Mechanisms<'a> {
    /// The held-back gradients, one per parameter (the MLP weights' never held, so zero).
    pub held: Option<Sparse>,
    /// The table's bounds.
    pub bounds: Option<Cow<'a, super::hooks::TableBounds>>,
}

/// An optimizer's state, laid out in the document as tiny-cuda-nn serialises its NeRF
/// optimizer into a snapshot saved with optimizer state (`Ema::serialize` ∘
/// `ExponentialDecay::serialize` ∘ `Adam::serialize`, keys sorted as nlohmann writes them):
/// instant-ngp loads a checkpoint with it and trains on. What an exact resume needs
/// besides (a backend's own EMA accumulators) goes under `stegongp`, which tiny-cuda-nn
/// ignores.
pub struct OptimizerState<'a> {
    /// Its learning rates (written; the fingerprint's options hold them for a resume).
    pub config: super::optimizer::OptimizerConfig,
    /// Updates taken.
    pub step: u32,
    /// Adam's first and second moments and each parameter's update count.
    pub m: Cow<'a, [f32]>,
    pub v: Cow<'a, [f32]>,
    pub param_steps: Cow<'a, [u32]>,
    /// The debiased EMA weights that instant-ngp reads (written fp16, as the reference
    /// keeps them). Written, never read back: a backend goes on from its own `ema`, so a
    /// state read back holds none here (empty).
    pub published: Cow<'a, [f32]>,
    /// The EMA accumulators as the backend keeps them (not debiased).
    pub ema: Cow<'a, [f32]>,
    /// The CPU's: per group of [`super::optimizer::GROUP`] parameters, the step its EMA
    /// was last brought up to. `None` on the GPU, which brings every EMA up each step.
    pub ema_step: Option<Cow<'a, [u32]>>,
}

/// The kind of trainer a state goes back into, with the sizes of what only that kind
/// keeps ([`Waiting`], [`OptimizerState::ema_step`]).
#[derive(Clone, Copy, Debug)]
pub enum Device {
    Cpu {
        /// Gradient buffers, and the words of each one's touched-group bit set.
        workers: usize,
        touched_words: usize,
        /// Groups of the optimizer's lazily updated EMA.
        ema_groups: usize,
    },
    Gpu {
        /// The most rays a batch holds (the device's ray buffers).
        max_rays: u32,
    },
}

/// What a trainer expects of a state it takes back: a state of another shape is refused,
/// naming the field, before anything is copied.
pub struct Expect<'e> {
    pub fingerprint: &'e [(String, String)],
    pub device: Device,
    pub optimizer: super::optimizer::OptimizerConfig,
    /// Parameters, of which the first `n_matrix` are MLP weights (never held back).
    pub n_params: usize,
    pub n_matrix: usize,
    /// The hash table's entries and their features (the bounds' table).
    pub n_entries: usize,
    pub n_features: usize,
    /// Each scene's occupancy cells.
    pub scene_cells: Vec<usize>,
    /// Whether a training policy is installed.
    pub policy: bool,
    /// Scene 0's training images where its cameras are refined.
    pub refined_images: Option<usize>,
}

impl TrainerState<'_> {
    /// The document.
    pub fn to_value(&self) -> Value {
        let fingerprint = Value::Map(
            self.fingerprint
                .iter()
                .map(|(k, v)| (Value::from(k.as_str()), Value::from(v.as_str())))
                .collect(),
        );
        let mut doc = vec![
            ("format", Value::from(FORMAT)),
            ("version", Value::from(VERSION)),
            ("fingerprint", fingerprint),
            ("step", Value::from(self.step)),
            ("weight_steps", Value::from(self.weight_steps)),
            ("params", f32s(&self.params)),
            ("optimizer", self.optimizer.to_value()),
        ];
        if let Some(c) = &self.occupancy_clock {
            let clock = map(vec![
                ("since", u64s(&c.since)),
                ("updates", Value::from(c.updates)),
            ]);
            doc.push(("occupancy_clock", clock));
        }
        let scenes = self.scenes.iter().map(Scene::to_value).collect();
        doc.push(("scenes", Value::Array(scenes)));
        let mechanisms = self.mechanisms.as_ref().map_or(Value::Nil, |m| {
            map(vec![
                ("held", m.held.as_ref().map_or(Value::Nil, Sparse::to_value)),
                ("bounds", bounds_value(m.bounds.as_deref())),
            ])
        });
        doc.push(("mechanisms", mechanisms));
        doc.push(match &self.waiting {
            Waiting::Workers(workers) => {
                let workers = workers
                    .iter()
                    .map(|w| {
                        map(vec![
                            ("grad", w.grad.to_value()),
                            ("touched", u64s(&w.touched)),
                        ])
                    })
                    .collect();
                ("workers", Value::Array(workers))
            }
            Waiting::Gradient(g) => ("gradient", g.as_ref().map_or(Value::Nil, Sparse::to_value)),
        });
        let policy = self
            .policy
            .as_ref()
            .map_or(Value::Nil, |p| Value::Binary(p.to_vec()));
        doc.push(("policy", policy));
        if let Some(c) = &self.cameras {
            let cameras = map(vec![
                ("offsets", f32s(&c.offsets)),
                ("m", f32s(&c.m)),
                ("v", f32s(&c.v)),
                ("updates", Value::from(c.updates)),
                ("pending", u64s(&c.pending)),
                ("pending_steps", Value::from(c.pending_steps)),
            ]);
            doc.push(("cameras", cameras));
        }
        map(doc)
    }
}

impl<'a> TrainerState<'a> {
    /// Reads back a [`Self::to_value`] (`doc`, named `origin` in errors) for a trainer
    /// that expects `e`: the header and fingerprint first ([`check_header`]), then every
    /// field, its length checked against the trainer's, before the trainer takes any.
    pub fn read(origin: &'a Path, doc: &'a Value, e: &Expect) -> Result<Self> {
        let f = Fields::top(origin, doc)?;
        check_header(&f, e.fingerprint)?;
        let step = f.u32("step")?;
        let weight_steps = f.u32("weight_steps")?;
        let mut params = crate::pages::zeroed(e.n_params);
        f.f32s_into("params", &mut params)?;
        let optimizer = OptimizerState::read(&f.map("optimizer")?, e)?;
        if optimizer.step != weight_steps || weight_steps > step {
            return Err(f.err(
                "weight_steps",
                format!(
                    "{weight_steps} of {step} steps, but the optimizer took {} steps",
                    optimizer.step
                ),
            ));
        }
        let occupancy_clock = match e.device {
            Device::Cpu { .. } => Some(OccupancyClock::read(
                &f.map("occupancy_clock")?,
                e.scene_cells.len(),
            )?),
            Device::Gpu { .. } => None,
        };
        let scenes = f
            .maps("scenes", e.scene_cells.len())?
            .iter()
            .zip(&e.scene_cells)
            .map(|(sf, &cells)| Scene::read(sf, cells, e.device))
            .collect::<Result<_>>()?;
        let mechanisms = match e.device {
            Device::Gpu { .. } if !e.policy => None,
            _ => Some(Mechanisms::read(&f.map("mechanisms")?, e)?),
        };
        let waiting = match e.device {
            Device::Cpu {
                workers,
                touched_words,
                ..
            } => Waiting::Workers(
                f.maps("workers", workers)?
                    .iter()
                    .map(|wf| {
                        let grad = wf.sparse("grad", e.n_params)?;
                        let mut touched = vec![0; touched_words];
                        wf.u64s_into("touched", &mut touched)?;
                        Ok(Worker {
                            grad,
                            touched: touched.into(),
                        })
                    })
                    .collect::<Result<_>>()?,
            ),
            Device::Gpu { .. } if e.policy => {
                Waiting::Gradient(Some(f.sparse("gradient", e.n_params)?))
            }
            Device::Gpu { .. } => Waiting::Gradient(None),
        };
        let policy = f.binary_opt("policy")?.map(Cow::Borrowed);
        let cameras = match e.refined_images {
            Some(n) => Some(read_cameras(&f.map("cameras")?, n)?),
            None => None,
        };
        Ok(TrainerState {
            fingerprint: e.fingerprint.to_vec(),
            step,
            weight_steps,
            params: params.into(),
            optimizer,
            occupancy_clock,
            scenes,
            mechanisms,
            waiting,
            policy,
            cameras,
        })
    }
}

/// A [`RefinerState`] of `n_images` images.
fn read_cameras(f: &Fields, n_images: usize) -> Result<RefinerState> {
    let n = n_images * 6;
    let (mut offsets, mut m, mut v, mut pending) =
        (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0; n]);
    f.f32s_into("offsets", &mut offsets)?;
    f.f32s_into("m", &mut m)?;
    f.f32s_into("v", &mut v)?;
    f.u64s_into("pending", &mut pending)?;
    Ok(RefinerState {
        offsets,
        m,
        v,
        updates: f.u32("updates")?,
        pending,
        pending_steps: f.u32("pending_steps")?,
    })
}

impl OccupancyClock<'_> {
    fn read(f: &Fields, n_scenes: usize) -> Result<Self> {
        // A single count: a state saved before each scene kept its own.
        let since = match f.u64("since") {
            Ok(one) => vec![one],
            Err(_) => {
                let mut v = vec![0; n_scenes];
                f.u64s_into("since", &mut v)?;
                v
            }
        };
        Ok(OccupancyClock {
            since: since.into(),
            updates: f.u32("updates")?,
        })
    }
}

impl Scene<'_> {
    fn to_value(&self) -> Value {
        let grid = &self.grid;
        map(vec![
            ("density", f32s(&grid.density)),
            ("bitfield", Value::Binary(grid.bitfield().to_vec())),
            ("mean", Value::F32(grid.mean)),
            ("grid_updates", Value::from(grid.ema_step)),
            ("rays_per_batch", Value::from(self.rays_per_batch)),
            ("measured_samples", Value::from(self.measured_samples)),
            ("measured_marched", Value::from(self.measured_marched)),
            ("march_stride", Value::from(self.march_stride)),
        ])
    }

    /// A scene's part for a grid of `cells` cells.
    fn read(f: &Fields, cells: usize, device: Device) -> Result<Self> {
        let mut density = crate::pages::zeroed::<f32>(cells);
        f.f32s_into("density", &mut density)?;
        let mut bitfield = vec![0u8; cells / 8];
        f.bytes_into("bitfield", &mut bitfield)?;
        let grid = crate::occupancy::OccupancyGrid::from_parts(
            density,
            bitfield,
            f.f32("mean")?,
            f.u32("grid_updates")?,
        )
        .ok_or_else(|| f.err("density", "does not make an occupancy grid"))?;
        let rays = f.u32("rays_per_batch")?;
        let (samples, marched) = (f.u32("measured_samples")?, f.u32("measured_marched")?);
        // Absent from states saved before the coarse march: they marched the reference's step.
        let stride = if f.has("march_stride") {
            f.u32("march_stride")?
        } else {
            1
        };
        let max_stride = 1 << super::coarse::MAX_STRIDE_LOG2;
        if !stride.is_power_of_two() || stride > max_stride {
            return Err(f.err(
                "march_stride",
                format!("{stride}: not a power of two up to {max_stride}"),
            ));
        }
        if let Device::Gpu { max_rays } = device {
            if stride != 1 {
                return Err(f.err(
                    "march_stride",
                    format!("{stride}: a GPU marches the reference's step (1)"),
                ));
            }
            // The device's ray buffers hold `max_rays` rays.
            if rays == 0 || rays > max_rays {
                return Err(f.err(
                    "rays_per_batch",
                    format!("{rays}: a batch has 1 to {max_rays} rays"),
                ));
            }
        }
        Ok(Scene {
            grid: Cow::Owned(grid),
            rays_per_batch: rays,
            measured_samples: samples,
            measured_marched: marched,
            march_stride: stride,
        })
    }
}

impl Mechanisms<'_> {
    fn read(f: &Fields, e: &Expect) -> Result<Self> {
        let held = if f.has("held") {
            let held = f.sparse("held", e.n_params)?;
            if held.nonzero_below(e.n_matrix) {
                return Err(f.err("held", "holds back an MLP gradient (never held)"));
            }
            Some(held)
        } else {
            None
        };
        let bounds = bounds_from(f, "bounds", e.n_entries, e.n_features)?;
        Ok(Mechanisms {
            held,
            bounds: bounds.map(Cow::Owned),
        })
    }
}

impl OptimizerState<'_> {
    fn to_value(&self) -> Value {
        let c = self.config;
        let lr = c.learning_rate(self.step);
        let ema16 = crate::snapshot::write::fp16_bytes(&self.published);
        let adam = map(vec![
            ("base_learning_rate", Value::F32(lr)),
            ("current_step", Value::from(self.step)),
            ("first_moments_binary", f32s(&self.m)),
            ("param_steps_binary", u32s(&self.param_steps)),
            ("second_moments_binary", f32s(&self.v)),
        ]);
        let decay = map(vec![
            ("learning_rate", Value::F32(c.lr)),
            ("learning_rate_factor", Value::F32(lr / c.lr)),
            ("nested", adam),
        ]);
        let mut ours = vec![("ema", f32s(&self.ema))];
        if let Some(s) = &self.ema_step {
            ours.push(("ema_step", u32s(s)));
        }
        map(vec![
            ("nested", decay),
            ("stegongp", map(ours)),
            ("weights_ema_binary", Value::Binary(ema16)),
        ])
    }

    /// Checked: a step count bounded before any table is grown to it, no parameter (nor
    /// EMA group) counting more updates than the optimizer.
    fn read(o: &Fields, e: &Expect) -> Result<Self> {
        let n = e.n_params;
        let (mut m, mut v) = (crate::pages::zeroed(n), crate::pages::zeroed(n));
        let mut param_steps = crate::pages::zeroed(n);
        let adam = o.map("nested")?.map("nested")?;
        adam.f32s_into("first_moments_binary", &mut m)?;
        adam.f32s_into("second_moments_binary", &mut v)?;
        adam.u32s_into("param_steps_binary", &mut param_steps)?;
        let step = adam.u32("current_step")?;
        // The bias-correction tables hold a value a step: a forged count must not make
        // them gigabytes (the fuzzer's first run of training states found 2^30).
        if step > super::optimizer::MAX_STEPS {
            return Err(adam.err(
                "current_step",
                format!(
                    "{step}: more steps than a training runs (at most {})",
                    super::optimizer::MAX_STEPS
                ),
            ));
        }
        if let Some(bad) = param_steps.iter().find(|&&s| s > step) {
            return Err(adam.err(
                "param_steps_binary",
                format!("a step count {bad} beyond the optimizer's {step}"),
            ));
        }
        let ours = o.map("stegongp")?;
        let mut ema = crate::pages::zeroed(n);
        ours.f32s_into("ema", &mut ema)?;
        let ema_step = match e.device {
            Device::Cpu { ema_groups, .. } => {
                let mut s = vec![0; ema_groups];
                ours.u32s_into("ema_step", &mut s)?;
                if let Some(bad) = s.iter().find(|&&s| s > step) {
                    return Err(ours.err(
                        "ema_step",
                        format!("a step count {bad} beyond the optimizer's {step}"),
                    ));
                }
                Some(s.into())
            }
            Device::Gpu { .. } => None,
        };
        Ok(OptimizerState {
            config: e.optimizer,
            step,
            m: m.into(),
            v: v.into(),
            param_steps: param_steps.into(),
            published: Cow::Borrowed(&[]),
            ema: ema.into(),
            ema_step,
        })
    }
}

/// An array of which most values are zero, as the document holds it: the values whose
/// bits are not zero (−0.0 included), with their indices, strictly increasing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Sparse {
    pub index: Vec<u32>,
    pub value: Vec<f32>,
}

impl Sparse {
    pub fn of(v: &[f32]) -> Self {
        let mut s = Sparse::default();
        for (i, x) in v.iter().enumerate() {
            if x.to_bits() != 0 {
                s.index.push(i as u32);
                s.value.push(*x);
            }
        }
        s
    }

    pub fn to_value(&self) -> Value {
        map(vec![
            ("index", u32s(&self.index)),
            ("value", f32s(&self.value)),
        ])
    }

    /// Into `out` (zeroed first), which is as long as the array read ([`Fields::sparse`]).
    pub fn scatter_into(&self, out: &mut [f32]) {
        out.fill(0.0);
        for (&i, &v) in self.index.iter().zip(&self.value) {
            out[i as usize] = v;
        }
    }

    /// The dense array of `n` values.
    pub fn dense(&self, n: usize) -> Vec<f32> {
        let mut out = vec![0.0; n];
        self.scatter_into(&mut out);
        out
    }

    /// Whether a value below index `n` is not zero (−0.0 counting as zero).
    fn nonzero_below(&self, n: usize) -> bool {
        self.index
            .iter()
            .zip(&self.value)
            .any(|(&i, &v)| (i as usize) < n && v != 0.0)
    }
}

/// A policy's table bounds ([`super::hooks::TableBounds`]) as `{entries, bounds}`, the
/// bounded entries alone; nil before a policy set any.
fn bounds_value(b: Option<&super::hooks::TableBounds>) -> Value {
    let Some(b) = b else {
        return Value::Nil;
    };
    let bounded: Vec<u32> = (0..b.bounds().len() as u32)
        .filter(|&e| b.is_bounded(e as usize))
        .collect();
    let values: Vec<f32> = bounded.iter().map(|&e| b.bound(e as usize)).collect();
    map(vec![("entries", u32s(&bounded)), ("bounds", f32s(&values))])
}

/// Takes back a [`bounds_value`] (field `key` of `f`) for a table of `n_entries` entries of
/// `n_features`: entries in order and within the table, bounds finite and ≥ 0.
fn bounds_from(
    f: &Fields,
    key: &str,
    n_entries: usize,
    n_features: usize,
) -> Result<Option<super::hooks::TableBounds>> {
    if !f.has(key) {
        return Ok(None);
    }
    let bf = f.map(key)?;
    let entries = bf.u32s("entries", n_entries)?;
    let mut values = vec![0.0f32; entries.len()];
    bf.f32s_into("bounds", &mut values)?;
    let mut bound = vec![super::hooks::UNBOUNDED; n_entries];
    let mut next = 0;
    for (&e, &b) in entries.iter().zip(&values) {
        if (e as usize) < next || e as usize >= n_entries || !(b >= 0.0 && b.is_finite()) {
            return Err(bf.err(
                "entries",
                format!("entry {e} out of order, past {n_entries}, or with bound {b}"),
            ));
        }
        bound[e as usize] = b;
        next = e as usize + 1;
    }
    Ok(Some(super::hooks::TableBounds::from_bounds(
        bound, n_features,
    )))
}

/// Reads fields of one map of the document; errors name the file and the field's path.
pub struct Fields<'a> {
    origin: &'a Path,
    at: String,
    entries: &'a [(Value, Value)],
}

impl<'a> Fields<'a> {
    pub fn top(origin: &'a Path, v: &'a Value) -> Result<Self> {
        match v {
            Value::Map(m) => Ok(Fields {
                origin,
                at: String::new(),
                entries: m,
            }),
            _ => Err(Error::format(origin, "a training state is a msgpack map")),
        }
    }

    pub fn err(&self, key: &str, msg: impl std::fmt::Display) -> Error {
        Error::format(self.origin, format!("field {}{key}: {msg}", self.at))
    }

    fn get(&self, key: &str) -> Result<&'a Value> {
        self.entries
            .iter()
            .find(|(k, _)| k.as_str() == Some(key))
            .map(|(_, v)| v)
            .ok_or_else(|| self.err(key, "missing"))
    }

    pub fn str(&self, key: &str) -> Result<&'a str> {
        self.get(key)?
            .as_str()
            .ok_or_else(|| self.err(key, "expected a string"))
    }

    pub fn u64(&self, key: &str) -> Result<u64> {
        self.get(key)?
            .as_u64()
            .ok_or_else(|| self.err(key, "expected a whole number"))
    }

    /// The document's `format` is `format`, else an error calling it not `what`.
    pub fn expect_format(&self, format: &str, what: &str) -> Result<()> {
        if self.str("format")? != format {
            return Err(self.err("format", format!("not {what} ({format})")));
        }
        Ok(())
    }

    /// The document's `version` is `version`, the only one this program reads.
    pub fn expect_version(&self, version: u64) -> Result<()> {
        let v = self.u64("version")?;
        if v != version {
            return Err(self.err(
                "version",
                format!("{v}: this program reads version {version}"),
            ));
        }
        Ok(())
    }

    pub fn u32(&self, key: &str) -> Result<u32> {
        u32::try_from(self.u64(key)?).map_err(|_| self.err(key, "larger than 2^32 − 1"))
    }

    pub fn f64(&self, key: &str) -> Result<f64> {
        match self.get(key)? {
            Value::F32(x) => Ok(*x as f64),
            Value::F64(x) => Ok(*x),
            Value::Integer(i) => i.as_f64().ok_or_else(|| self.err(key, "expected a number")),
            _ => Err(self.err(key, "expected a number")),
        }
    }

    /// A nested document as it is.
    pub fn value(&self, key: &str) -> Result<&'a Value> {
        self.get(key)
    }

    /// Binary data of any length (a nested document).
    pub fn binary(&self, key: &str) -> Result<&'a [u8]> {
        match self.get(key)? {
            Value::Binary(b) => Ok(b),
            _ => Err(self.err(key, "expected binary data")),
        }
    }

    /// Binary data of any length, or `None` where the field is absent or nil.
    pub fn binary_opt(&self, key: &str) -> Result<Option<&'a [u8]>> {
        if self.has(key) {
            self.binary(key).map(Some)
        } else {
            Ok(None)
        }
    }

    /// Whether the field is present and not nil.
    pub fn has(&self, key: &str) -> bool {
        self.get(key).is_ok_and(|v| !v.is_nil())
    }

    pub fn f32(&self, key: &str) -> Result<f32> {
        match self.get(key)? {
            Value::F32(x) => Ok(*x),
            Value::F64(x) => Ok(*x as f32),
            _ => Err(self.err(key, "expected a number")),
        }
    }

    fn bin(&self, key: &str, len: usize, width: usize) -> Result<&'a [u8]> {
        match self.get(key)? {
            Value::Binary(b) if b.len() == len * width => Ok(b),
            Value::Binary(b) => Err(self.err(
                key,
                format!(
                    "{} bytes where this training has {len} values of {width} bytes",
                    b.len()
                ),
            )),
            _ => Err(self.err(key, "expected binary data")),
        }
    }

    /// `len` f32 values into `out` (whose length is `len`).
    pub fn f32s_into(&self, key: &str, out: &mut [f32]) -> Result<()> {
        let b = self.bin(key, out.len(), 4)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(4)) {
            *o = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        Ok(())
    }

    pub fn u32s_into(&self, key: &str, out: &mut [u32]) -> Result<()> {
        let b = self.bin(key, out.len(), 4)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(4)) {
            *o = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        Ok(())
    }

    /// A [`Sparse`] array of `n` values: indices strictly increasing and below `n`, one
    /// value each.
    pub fn sparse(&self, key: &str, n: usize) -> Result<Sparse> {
        let f = self.map(key)?;
        let (index, value) = (f.binary("index")?, f.binary("value")?);
        if index.len() % 4 != 0 || index.len() != value.len() || index.len() / 4 > n {
            return Err(self.err(
                key,
                format!(
                    "{} index and {} value bytes for at most {n} values",
                    index.len(),
                    value.len(),
                ),
            ));
        }
        let mut out = Sparse::default();
        let mut next = 0usize;
        for (i, v) in index.chunks_exact(4).zip(value.chunks_exact(4)) {
            let i = u32::from_le_bytes([i[0], i[1], i[2], i[3]]);
            if (i as usize) < next || i as usize >= n {
                return Err(self.err(key, format!("index {i} out of order or past {n} values")));
            }
            out.index.push(i);
            out.value.push(f32::from_le_bytes([v[0], v[1], v[2], v[3]]));
            next = i as usize + 1;
        }
        Ok(out)
    }

    /// u32 values of any count up to `max`.
    pub fn u32s(&self, key: &str, max: usize) -> Result<Vec<u32>> {
        let b = self.binary(key)?;
        if b.len() % 4 != 0 || b.len() / 4 > max {
            return Err(self.err(
                key,
                format!(
                    "{} bytes where at most {max} values of 4 bytes fit",
                    b.len()
                ),
            ));
        }
        Ok(b.chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    /// `out.len()` words of a [`u64s`] into `out`.
    pub fn u64s_into(&self, key: &str, out: &mut [u64]) -> Result<()> {
        let b = self.bin(key, out.len(), 8)?;
        for (o, c) in out.iter_mut().zip(b.chunks_exact(8)) {
            *o = u64::from_le_bytes(c.try_into().expect("8 bytes"));
        }
        Ok(())
    }

    pub fn bytes_into(&self, key: &str, out: &mut [u8]) -> Result<()> {
        out.copy_from_slice(self.bin(key, out.len(), 1)?);
        Ok(())
    }

    pub fn map(&self, key: &str) -> Result<Fields<'a>> {
        match self.get(key)? {
            Value::Map(m) => Ok(Fields {
                origin: self.origin,
                at: format!("{}{key}.", self.at),
                entries: m,
            }),
            _ => Err(self.err(key, "expected a map")),
        }
    }

    /// The maps of an array that must hold exactly `n`.
    pub fn maps(&self, key: &str, n: usize) -> Result<Vec<Fields<'a>>> {
        let a = match self.get(key)? {
            Value::Array(a) if a.len() == n => a,
            Value::Array(a) => {
                return Err(self.err(
                    key,
                    format!("{} entries where this training has {n}", a.len()),
                ));
            }
            _ => return Err(self.err(key, "expected an array")),
        };
        a.iter()
            .enumerate()
            .map(|(i, v)| match v {
                Value::Map(m) => Ok(Fields {
                    origin: self.origin,
                    at: format!("{}{key}[{i}].", self.at),
                    entries: m,
                }),
                _ => Err(self.err(&format!("{key}[{i}]"), "expected a map")),
            })
            .collect()
    }
}

/// The parts of a training a saved state must share with the trainer it goes back into, by
/// name: the device kind (`None`: the CPU, whose states predate the entry), the layout and
/// options, whether a policy is installed, and each scene's image count, size and box.
/// Never the index functions: a state's errors may be printed, and a key must not be (the
/// program re-derives them from the same key files).
pub fn fingerprint<'a>(
    device: Option<&str>,
    layout: &crate::network::ModelConfig,
    options: &super::TrainConfig,
    policy: bool,
    scenes: impl ExactSizeIterator<Item = &'a crate::data::Dataset>,
) -> Vec<(String, String)> {
    let mut out: Vec<(String, String)> = device
        .map(|d| (DEVICE.to_string(), d.to_string()))
        .into_iter()
        .collect();
    out.extend([
        ("layout".to_string(), format!("{layout:?}")),
        ("options".to_string(), format!("{options:?}")),
        ("scenes".to_string(), scenes.len().to_string()),
        (
            "policy".to_string(),
            if policy { "installed" } else { "none" }.to_string(),
        ),
    ]);
    for (i, d) in scenes.enumerate() {
        let size = d
            .frames
            .first()
            .map_or((0, 0), |f| (f.camera.width, f.camera.height));
        out.push((
            format!("scene {i}"),
            format!(
                "{} images of {}x{}, aabb {}",
                d.frames.len(),
                size.0,
                size.1,
                d.aabb_scale
            ),
        ));
    }
    out
}

/// Parses a state document.
pub fn open(origin: &Path, bytes: &[u8]) -> Result<Value> {
    msgpack::decode(bytes).map_err(|e| Error::format(origin, e))
}

/// Checks a state's format, version and fingerprint; a difference is named, not shown
/// (a hidden scene's description stays out of messages).
pub fn check_header(f: &Fields, fingerprint: &[(String, String)]) -> Result<()> {
    f.expect_format(FORMAT, "a training state")?;
    f.expect_version(VERSION)?;
    let saved = f.map("fingerprint")?;
    // A state holds what its own kind of trainer keeps between steps: the CPU's and the
    // GPU's are not interchangeable, and saying so beats naming the options that differ.
    let device_of = |d: Option<&str>| match d {
        None | Some("cpu") => "the CPU",
        Some("gpu") => "the GPU",
        Some(_) => "an unknown device",
    };
    let want = device_of(
        fingerprint
            .iter()
            .find(|(k, _)| k == DEVICE)
            .map(|(_, v)| v.as_str()),
    );
    let got = device_of(saved.str(DEVICE).ok());
    if got != want {
        return Err(f.err(
            "fingerprint",
            format!(
                "saved by training on {got}; this run trains on {want} (a state goes on only \
                 on the kind of device that saved it)"
            ),
        ));
    }
    let mut differ: Vec<&str> = fingerprint
        .iter()
        .filter(|(k, v)| saved.str(k).map_or(true, |s| s != v))
        .map(|(k, _)| k.as_str())
        .collect();
    // A key only the saved fingerprint has differs too (camera refinement's is there only
    // where a run refines): that part of the state would be dropped. Named escaped, as
    // the file wrote it.
    let only_saved: Vec<String> = (saved.entries.iter())
        .filter_map(|(k, _)| k.as_str())
        .filter(|k| *k != DEVICE && !fingerprint.iter().any(|(ours, _)| ours == k))
        .map(|k| k.escape_debug().to_string())
        .collect();
    differ.extend(only_saved.iter().map(String::as_str));
    if !differ.is_empty() {
        return Err(f.err(
            "fingerprint",
            format!(
                "saved by a different training: its {} differ from this run's (the same data, keys, model, options and thread count are needed to go on)",
                differ.join(", ")
            ),
        ));
    }
    Ok(())
}
