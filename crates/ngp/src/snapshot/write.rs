//! Snapshot → msgpack document, key for key as `Testbed::save_snapshot` and tcnn's
//! `Trainer::serialize` fill it (types as the C++ members have them).

use super::msgpack::{binary_bytes, encode, f, fv, i, map, s, u};
use super::read::config_from_value;
use super::{
    Aabb, DENSITY_GRID_CELLS, DENSITY_GRID_SIZE, Lens, SNAPSHOT_VERSION, Snapshot, SnapshotDataset,
    config, n_cascades,
};
use crate::error::{Error, Result};
use crate::network::NerfLayout;
use half::slice::HalfFloatSliceExt;
use rmpv::Value;

pub fn to_msgpack(snap: &Snapshot) -> Result<Vec<u8>> {
    let layout = NerfLayout::new(snap.config)?;
    let aabb_scale = snap.config.aabb_scale;
    if !aabb_scale.is_power_of_two() || aabb_scale > super::MAX_AABB_SCALE {
        return Err(Error::Config(format!(
            "aabb_scale must be a power of two ≤ 128, got {aabb_scale}"
        )));
    }
    if snap.params.len() != layout.n_params {
        return Err(Error::Config(format!(
            "snapshot has {} parameters, the model needs {}",
            snap.params.len(),
            layout.n_params
        )));
    }
    let grid_len = DENSITY_GRID_CELLS * n_cascades(aabb_scale);
    if !snap.density_grid.is_empty() && snap.density_grid.len() != grid_len {
        return Err(Error::Config(format!(
            "density grid has {} cells, expected {grid_len}",
            snap.density_grid.len()
        )));
    }

    let mut top: Vec<(Value, Value)> = match &snap.preserved.network_config {
        Some(Value::Map(m)) if config_from_value(m).ok() == Some(snap.config.grid) => m
            .iter()
            .filter(|(k, _)| k.as_str() != Some("snapshot"))
            .cloned()
            .collect(),
        _ => config::network_config(&snap.config.grid)
            .into_iter()
            .map(|(k, v)| (s(k), v))
            .collect(),
    };
    top.push((s("snapshot"), snapshot_value(snap, layout.n_params)));
    let doc = Value::Map(top);
    // Sized once: a checkpoint's optimizer and run state are hundreds of megabytes, and a
    // growing buffer would copy them several times over.
    let preserved = [&snap.preserved.optimizer, &snap.preserved.run_state]
        .into_iter()
        .flatten()
        .map(binary_bytes)
        .sum::<usize>();
    let mut out = Vec::with_capacity(
        layout.n_params * 4 + snap.density_grid.len() * 6 + preserved + (1 << 20),
    );
    encode(&doc, &mut out);
    Ok(out)
}

/// `v` as little-endian fp16, the reference's storage of weights and grids.
pub(crate) fn fp16_bytes(v: &[f32]) -> Vec<u8> {
    let mut h = vec![half::f16::ZERO; v.len()];
    h.convert_from_f32_slice(v);
    let mut out = Vec::with_capacity(v.len() * 2);
    for x in h {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn params_bytes(snap: &Snapshot) -> Vec<u8> {
    if snap.exact {
        f32_bytes(&snap.params)
    } else {
        fp16_bytes(&snap.params)
    }
}

/// Where an exact snapshot keeps its density grid at full precision.
pub(crate) const EXACT_DENSITY_KEY: &str = "stegongp_density_grid_float";

fn aabb(b: &Aabb) -> Value {
    map(vec![("min", fv(&b.min)), ("max", fv(&b.max))])
}

fn rows<const N: usize>(m: &[[f32; N]]) -> Value {
    Value::Array(m.iter().map(|r| fv(r)).collect())
}

fn ivec(v: &[i32]) -> Value {
    Value::Array(v.iter().map(|x| i(*x as i64)).collect())
}

fn lens(l: &Lens) -> Value {
    match *l {
        Lens::Perspective => Value::Nil,
        Lens::OpenCv { k1, k2, p1, p2 } => map(vec![
            ("is_fisheye", Value::Boolean(false)),
            ("k1", f(k1)),
            ("k2", f(k2)),
            ("p1", f(p1)),
            ("p2", f(p2)),
        ]),
        Lens::OpenCvFisheye { k1, k2, k3, k4 } => map(vec![
            ("is_fisheye", Value::Boolean(true)),
            ("k1", f(k1)),
            ("k2", f(k2)),
            ("k3", f(k3)),
            ("k4", f(k4)),
        ]),
        Lens::FTheta { p, w, h } => map(vec![
            ("ftheta_p0", f(p[0])),
            ("ftheta_p1", f(p[1])),
            ("ftheta_p2", f(p[2])),
            ("ftheta_p3", f(p[3])),
            ("ftheta_p4", f(p[4])),
            ("w", f(w)),
            ("h", f(h)),
        ]),
        Lens::LatLong => map(vec![("latlong", Value::Boolean(true))]),
        Lens::Equirectangular => map(vec![("equirectangular", Value::Boolean(true))]),
        Lens::Orthographic => map(vec![("orthographic", Value::Boolean(true))]),
    }
}

fn dataset(d: &SnapshotDataset, aabb_scale: u32) -> Value {
    let mut e = vec![
        ("n_images", u(d.images.len() as u64)),
        (
            "paths",
            Value::Array(d.paths.iter().map(|p| s(p)).collect()),
        ),
    ];
    // The reference emits these two arrays only when there is at least one image.
    if !d.images.is_empty() {
        let meta = d
            .images
            .iter()
            .map(|im| {
                map(vec![
                    ("focal_length", fv(&im.focal_length)),
                    ("lens", lens(&im.lens)),
                    ("principal_point", fv(&im.principal_point)),
                    ("rolling_shutter", fv(&im.rolling_shutter)),
                    ("resolution", ivec(&im.resolution)),
                ])
            })
            .collect();
        let xforms = d
            .images
            .iter()
            .map(|im| {
                map(vec![
                    ("start", rows(&im.xform_start)),
                    ("end", rows(&im.xform_end)),
                ])
            })
            .collect();
        e.push(("metadata", Value::Array(meta)));
        e.push(("xforms", Value::Array(xforms)));
    }
    e.extend([
        ("render_aabb", aabb(&d.render_aabb)),
        ("render_aabb_to_local", rows(&d.render_aabb_to_local)),
        ("up", fv(&d.up)),
        ("offset", fv(&d.offset)),
        ("envmap_resolution", ivec(&d.envmap_resolution)),
        ("scale", f(d.scale)),
        // Always equal to the nerf-level aabb_scale in the reference.
        ("aabb_scale", i(aabb_scale as i64)),
        ("from_mitsuba", Value::Boolean(d.from_mitsuba)),
        ("is_hdr", Value::Boolean(d.is_hdr)),
        (
            "wants_importance_sampling",
            Value::Boolean(d.wants_importance_sampling),
        ),
        ("n_extra_learnable_dims", u(d.n_extra_learnable_dims as u64)),
    ]);
    map(e)
}

/// Per-image Adam state of a run without camera optimisation (`AdamOptimizer(1e-4f)`).
fn idle_adam(n_images: usize, dims: usize) -> Value {
    let zeros = vec![0.0f32; dims];
    let one = map(vec![
        ("iter", u(0)),
        ("first_moment", fv(&zeros)),
        ("second_moment", fv(&zeros)),
        ("variable", fv(&zeros)),
        ("learning_rate", f(1e-4)),
        ("epsilon", f(1e-8)),
        ("beta1", f(0.9)),
        ("beta2", f(0.99)),
    ]);
    Value::Array(vec![one; n_images])
}

fn snapshot_value(snap: &Snapshot, n_params: usize) -> Value {
    let aabb_scale = snap.config.aabb_scale;
    let empty_dataset;
    let ds = match &snap.dataset {
        Some(d) => d,
        None => {
            // `create_empty_nerf_dataset(0, aabb_scale)`.
            empty_dataset = SnapshotDataset::new(Vec::new(), Vec::new(), aabb_scale);
            &empty_dataset
        }
    };
    let n_images = ds.images.len();
    let p = &snap.preserved;
    let nerf = map(vec![
        ("aabb_scale", i(aabb_scale as i64)),
        (
            "cam_pos_offset",
            p.cam_pos_offset
                .clone()
                .unwrap_or_else(|| idle_adam(n_images, 3)),
        ),
        (
            "cam_rot_offset",
            p.cam_rot_offset
                .clone()
                .unwrap_or_else(|| idle_adam(n_images, 3)),
        ),
        (
            "extra_dims_opt",
            p.extra_dims_opt
                .clone()
                .unwrap_or_else(|| idle_adam(n_images, 0)),
        ),
        (
            "rgb",
            map(vec![
                ("rays_per_batch", u(snap.rays_per_batch as u64)),
                ("measured_batch_size", u(snap.measured_batch_size as u64)),
                (
                    "measured_batch_size_before_compaction",
                    u(snap.measured_batch_size_before_compaction as u64),
                ),
            ]),
        ),
        ("dataset", dataset(ds, aabb_scale)),
    ]);
    let c = &snap.camera;
    let camera = map(vec![
        ("matrix", rows(&c.matrix)),
        ("fov_axis", u(c.fov_axis as u64)),
        ("relative_focal_length", fv(&c.relative_focal_length)),
        ("screen_center", fv(&c.screen_center)),
        ("zoom", f(c.zoom)),
        ("scale", f(c.scale)),
        ("aperture_size", f(c.aperture_size)),
        ("autofocus", Value::Boolean(c.autofocus)),
        ("autofocus_target", fv(&c.autofocus_target)),
        ("autofocus_depth", f(c.autofocus_depth)),
    ]);
    let v = &snap.view;
    let mut e = vec![
        ("n_params", u(n_params as u64)),
        (
            "params_type",
            s(if snap.exact { "float" } else { "__half" }),
        ),
        ("params_binary", Value::Binary(params_bytes(snap))),
    ];
    if let Some(o) = &p.optimizer {
        e.push(("optimizer", o.clone()));
    }
    e.extend([
        ("version", u(SNAPSHOT_VERSION)),
        ("mode", s("nerf")),
        ("density_grid_size", u(DENSITY_GRID_SIZE as u64)),
        (
            "density_grid_binary",
            Value::Binary(fp16_bytes(&snap.density_grid)),
        ),
        ("nerf", nerf),
        ("training_step", u(snap.training_step as u64)),
        ("loss", f(snap.loss)),
        ("aabb", aabb(&v.aabb)),
        ("bounding_radius", f(v.bounding_radius)),
        ("render_aabb_to_local", rows(&v.render_aabb_to_local)),
        ("render_aabb", aabb(&v.render_aabb)),
        ("up_dir", fv(&v.up_dir)),
        ("sun_dir", fv(&v.sun_dir)),
        ("exposure", f(v.exposure)),
        ("background_color", fv(&v.background_color)),
        ("camera", camera),
    ]);
    if snap.exact {
        e.push((
            EXACT_DENSITY_KEY,
            Value::Binary(f32_bytes(&snap.density_grid)),
        ));
    }
    if let Some(r) = &p.run_state {
        e.push(("stegongp_run_state", r.clone()));
    }
    map(e)
}
