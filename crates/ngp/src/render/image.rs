//! Rendering whole images: rays of a camera marched in waves (a few samples per live ray
//! per wave, so rays that hit a surface stop early), composited until the transmittance
//! drops below a threshold, over a background colour.

use super::composite::composite;
use super::march::Marcher;
use crate::camera::Camera;
use crate::encoding::LevelIndices;
use crate::encoding::grid::GridTable;
use crate::network::nerf::{CHUNK, NerfNetwork, Workspace};
use crate::occupancy::OccupancyGrid;
use rayon::prelude::*;
use std::time::Instant;

/// The background a rendering is composited over. White is our scoring default (the NeRF
/// literature's synthetic-scene scores); instant-ngp's `scripts/run.py` scores on black
/// (`eval --protocol instant-ngp`), and its testbed's default background is black too.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Background {
    #[default]
    White,
    Black,
}

impl crate::choice::Choice for Background {
    const ALL: &'static [Self] = &[Background::White, Background::Black];
    fn name(self) -> &'static str {
        match self {
            Background::White => "white",
            Background::Black => "black",
        }
    }
    fn help(self) -> &'static str {
        match self {
            Background::White => {
                "white (ours and the NeRF literature's; instant-ngp's run.py scores on black)"
            }
            Background::Black => "black",
        }
    }
}

impl std::fmt::Display for Background {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(crate::choice::Choice::name(*self))
    }
}

impl Background {
    /// The colour, for [`RenderOptions::background`].
    pub fn rgb(self) -> [f32; 3] {
        match self {
            Background::White => [1.0; 3],
            Background::Black => [0.0; 3],
        }
    }
}

/// Where instant-ngp stops a ray when it scores held-out views (`scripts/run.py` sets it
/// before rendering the test set): `eval`'s default, and [`RenderOptions::default`]'s.
pub const SCORING_MIN_TRANSMITTANCE: f32 = 1e-4;

/// Where instant-ngp stops a ray for everything else it renders (the testbed's default:
/// screenshots, videos and its viewer): `render`'s, `video`'s and `view`'s default. Fewer
/// samples behind surfaces, for a change the eye hardly sees (benchmarks/engine.md).
pub const VIEWING_MIN_TRANSMITTANCE: f32 = 0.01;

#[derive(Clone, Copy, Debug)]
pub struct RenderOptions {
    /// Background colour (sRGB, [0,1]); [`Background::rgb`] gives the usual two.
    pub background: [f32; 3],
    /// A ray stops below this transmittance ([`SCORING_MIN_TRANSMITTANCE`] by default).
    pub min_transmittance: f32,
    /// Samples marched per live ray per wave. (The reference's GPU renderer marches
    /// `clamp(rays / live rays, 1, 8)` between compactions; on the CPU the smaller waves'
    /// overhead cost more than the samples they save: 25.9 s against 22.9 s for three
    /// fox-colmap views, benchmarks/engine.md.)
    pub samples_per_wave: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            background: [1.0; 3],
            min_transmittance: SCORING_MIN_TRANSMITTANCE,
            samples_per_wave: 8,
        }
    }
}

/// A rendered view: RGB (interleaved, [0,1]), expected depth (ngp units, normalised by
/// opacity) and opacity per pixel.
#[derive(Clone, Debug)]
pub struct RenderedImage {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
    /// Network samples evaluated.
    pub n_samples: u64,
    /// Where the rendering's time went (the CPU renderer's; zero elsewhere).
    pub profile: RenderProfile,
}

impl RenderedImage {
    /// Network samples a ray that entered the scene's box; `None` where no ray did or the
    /// renderer keeps no profile (a GPU's).
    pub fn samples_per_ray(&self) -> Option<f64> {
        (self.profile.n_rays > 0).then(|| self.n_samples as f64 / self.profile.n_rays as f64)
    }

    /// ", 52 samples a ray; march 28% · network 70% · composite 2%" for a progress line, or
    /// nothing where the renderer keeps no profile.
    pub fn profile_note(&self) -> String {
        self.samples_per_ray()
            .map(|n| format!(", {n:.0} samples a ray; {}", self.profile.split()))
            .unwrap_or_default()
    }
}

/// Where a CPU rendering's time went: seconds summed over the threads, so the phases' shares
/// are what counts, and how many rays entered the box.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderProfile {
    /// Rays that entered the scene's box.
    pub n_rays: u64,
    /// Waves of samples marched.
    pub n_waves: u64,
    pub march_seconds: f64,
    pub network_seconds: f64,
    pub composite_seconds: f64,
}

impl RenderProfile {
    fn add(&mut self, o: &RenderProfile) {
        self.n_rays += o.n_rays;
        self.n_waves += o.n_waves;
        self.march_seconds += o.march_seconds;
        self.network_seconds += o.network_seconds;
        self.composite_seconds += o.composite_seconds;
    }

    /// "march 10% · network 85% · composite 5%".
    pub fn split(&self) -> String {
        let total = (self.march_seconds + self.network_seconds + self.composite_seconds).max(1e-12);
        format!(
            "march {:.0}% · network {:.0}% · composite {:.0}%",
            100.0 * self.march_seconds / total,
            100.0 * self.network_seconds / total,
            100.0 * self.composite_seconds / total
        )
    }
}

/// Everything needed to render one scene of a model.
pub struct SceneView<'a> {
    pub net: &'a NerfNetwork,
    pub params: &'a [f32],
    /// The grid block of `params` as fp16 bits, where every value is one: read instead of
    /// the f32 block, the same bits from half the memory.
    pub grid_f16: Option<&'a [u16]>,
    pub indices: &'a LevelIndices,
    pub grid: &'a OccupancyGrid,
    pub marcher: Marcher,
}

impl SceneView<'_> {
    /// The table the view's forwards read: the fp16 copy where there is one.
    pub fn grid_table(&self) -> GridTable<'_> {
        match self.grid_f16 {
            Some(t) => GridTable::F16(t),
            None => GridTable::F32(&self.params[self.net.layout.grid_offset..]),
        }
    }
}

struct LiveRay {
    pixel: usize,
    o: [f32; 3],
    d: [f32; 3],
    t: f32,
    tr: f32,
    rgb: [f32; 3],
    depth: f32,
}

const ROWS_PER_TASK: u32 = 2;

pub fn render_image(view: &SceneView, cam: &Camera, opts: &RenderOptions) -> RenderedImage {
    let (w, h) = (cam.width, cam.height);
    let n = (w * h) as usize;
    let mut rgb = vec![0.0f32; n * 3];
    let mut depth = vec![0.0f32; n];
    let mut opacity = vec![0.0f32; n];
    let rows = ROWS_PER_TASK as usize * w as usize;
    let render = Render {
        view,
        table: view.grid_table(),
        cam,
        opts,
    };
    let profiles: Vec<(u64, RenderProfile)> = rgb
        .par_chunks_mut(rows * 3)
        .zip(depth.par_chunks_mut(rows))
        .zip(opacity.par_chunks_mut(rows))
        .enumerate()
        .map_init(
            || (view.net.inference_workspace(), WaveBuffers::default()),
            |(ws, b), (task, ((rgb, depth), opacity))| {
                let mut out = Pixels {
                    rgb,
                    depth,
                    opacity,
                };
                render.task(task * rows, ws, b, &mut out)
            },
        )
        .collect();
    let mut profile = RenderProfile::default();
    for (_, p) in &profiles {
        profile.add(p);
    }
    RenderedImage {
        width: w,
        height: h,
        rgb,
        depth,
        opacity,
        n_samples: profiles.iter().map(|(n, _)| n).sum(),
        profile,
    }
}

/// What every task of one [`render_image`] reads.
struct Render<'a> {
    view: &'a SceneView<'a>,
    table: GridTable<'a>,
    cam: &'a Camera,
    opts: &'a RenderOptions,
}

/// A task's pixels (a band of whole rows) in the image's buffers.
struct Pixels<'a> {
    rgb: &'a mut [f32],
    depth: &'a mut [f32],
    opacity: &'a mut [f32],
}

impl Render<'_> {
    /// Renders the pixels `out` holds, the first of them pixel `first` of the image, in
    /// waves until every ray has stopped: the samples it evaluated and its profile.
    fn task(
        &self,
        first: usize,
        ws: &mut Workspace,
        b: &mut WaveBuffers,
        out: &mut Pixels,
    ) -> (u64, RenderProfile) {
        let mut prof = RenderProfile::default();
        self.start_rays(first, b, out);
        let n_rays = b.live.len();
        prof.n_rays = n_rays as u64;
        let mut n_samples = 0u64;
        while !b.live.is_empty() {
            let t_march = Instant::now();
            b.march(self.view, self.opts.samples_per_wave.max(1));
            let t_net = Instant::now();
            b.evaluate(self.view, self.table, ws);
            let t_comp = Instant::now();
            n_samples += b.pos.len() as u64;
            b.composite(self.opts, out);
            let t_end = Instant::now();
            prof.n_waves += 1;
            prof.march_seconds += (t_net - t_march).as_secs_f64();
            prof.network_seconds += (t_comp - t_net).as_secs_f64();
            prof.composite_seconds += (t_end - t_comp).as_secs_f64();
        }
        (n_samples, prof)
    }

    /// The task's rays that enter the box, into `b.live`; every pixel starts as the
    /// background.
    fn start_rays(&self, first: usize, b: &mut WaveBuffers, out: &mut Pixels) {
        let (view, w) = (self.view, self.cam.width as usize);
        b.live.clear();
        for k in 0..out.depth.len() {
            let p = first + k;
            let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
            let ray = self.cam.ray(x, y);
            if let Some((t0, _)) = view.marcher.intersect(ray.o, ray.d) {
                // Start half a step inside the box: the entry point itself may
                // round to just outside it and end the ray at once (the reference
                // also starts at a fractional step).
                let t = view.marcher.advance(t0, 0.5);
                b.live.push(LiveRay {
                    pixel: k,
                    o: ray.o,
                    d: ray.d,
                    t,
                    tr: 1.0,
                    rgb: [0.0; 3],
                    depth: 0.0,
                });
            }
            out.rgb[k * 3..k * 3 + 3].copy_from_slice(&self.opts.background);
        }
    }
}

/// A rendering thread's buffers, reused from wave to wave and task to task.
#[derive(Default)]
struct WaveBuffers {
    live: Vec<LiveRay>,
    pos: Vec<[f32; 3]>,
    dir: Vec<[f32; 3]>,
    dts: Vec<f32>,
    dist: Vec<f32>,
    raw: Vec<[f32; 4]>,
    /// (live ray, first sample, samples) of the wave.
    owner: Vec<(usize, usize, usize)>,
    done: Vec<bool>,
}

impl WaveBuffers {
    /// A wave's samples: up to `per_ray` from each live ray, which moves on past them
    /// (and is marked done where it leaves the grid).
    fn march(&mut self, view: &SceneView, per_ray: usize) {
        let WaveBuffers {
            live,
            pos,
            dir,
            dts,
            dist,
            raw: _,
            owner,
            done,
        } = self;
        pos.clear();
        dir.clear();
        dts.clear();
        dist.clear();
        owner.clear();
        done.clear();
        done.resize(live.len(), false);
        for (li, r) in live.iter_mut().enumerate() {
            let start = pos.len();
            let next = view
                .marcher
                .march(view.grid, r.o, r.d, r.t, per_ray, pos, dts, dist);
            let got = pos.len() - start;
            dir.extend(std::iter::repeat_n(r.d, got));
            owner.push((li, start, got));
            match next {
                Some(t) => r.t = t,
                None => done[li] = true,
            }
        }
    }

    /// The network's outputs for the wave's samples, into `raw`.
    fn evaluate(&mut self, view: &SceneView, table: GridTable, ws: &mut Workspace) {
        let (pos, dir, raw) = (&self.pos, &self.dir, &mut self.raw);
        raw.resize(pos.len(), [0.0f32; 4]);
        for (k, (p, d)) in pos.chunks(CHUNK).zip(dir.chunks(CHUNK)).enumerate() {
            let s = k * CHUNK;
            view.net.forward_with(
                view.params,
                table,
                view.indices,
                p,
                d,
                ws,
                &mut raw[s..s + p.len()],
            );
        }
    }

    /// Composites each live ray's samples of the wave onto it, then writes out and drops
    /// the rays that are done (out of the grid or below the transmittance threshold).
    fn composite(&mut self, opts: &RenderOptions, out: &mut Pixels) {
        let WaveBuffers {
            live,
            dts,
            dist,
            raw,
            owner,
            done,
            ..
        } = self;
        for &(li, start, got) in owner.iter() {
            let r = &mut live[li];
            let s = start..start + got;
            let c = composite(
                &raw[s.clone()],
                &dts[s.clone()],
                &dist[s],
                r.tr,
                opts.min_transmittance,
            );
            for k in 0..3 {
                r.rgb[k] += c.rgb[k];
            }
            r.depth += c.depth;
            r.tr = c.transmittance;
            if r.tr < opts.min_transmittance {
                done[li] = true;
            }
        }
        let mut li = 0;
        live.retain(|r| {
            let keep = !done[li];
            li += 1;
            if !keep {
                let k = r.pixel;
                let a = 1.0 - r.tr;
                for c in 0..3 {
                    out.rgb[k * 3 + c] = r.rgb[c] + r.tr * opts.background[c];
                }
                out.opacity[k] = a;
                out.depth[k] = if a > 0.0 { r.depth / a } else { 0.0 };
            }
            keep
        });
    }
}
