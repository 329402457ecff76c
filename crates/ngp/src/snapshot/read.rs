//! msgpack document → Snapshot, validating every field the engine relies on. Errors name the
//! field by its path (`snapshot.nerf.rgb.rays_per_batch`) and what was found there.

use super::msgpack::decode;
use super::{
    Aabb, DENSITY_GRID_CELLS, DENSITY_GRID_SIZE, DatasetImage, IDENTITY3, Lens, MAX_AABB_SCALE,
    Preserved, SNAPSHOT_VERSION, Snapshot, SnapshotCamera, SnapshotDataset, SnapshotView,
    n_cascades,
};
use crate::encoding::layout::{GridConfig, per_level_scale};
use crate::network::{ModelConfig, NerfLayout};
use rmpv::Value;
use std::io::Read;

type R<T> = std::result::Result<T, String>;

/// Largest decompressed document accepted; a corrupt stream cannot make us allocate more.
const MAX_DOCUMENT_BYTES: u64 = 4 << 30;

/// How a file was framed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Framing {
    Gzip,
    Zlib,
    Raw,
}

/// Strips gzip/zlib framing when the first two bytes say so (zstr's detection), else returns
/// the bytes as they are.
pub fn unframe(bytes: &[u8]) -> R<(Vec<u8>, Framing)> {
    if bytes.is_empty() {
        return Err("file is empty".into());
    }
    let framing = match bytes {
        [0x1f, 0x8b, ..] => Framing::Gzip,
        [0x78, 0x01 | 0x9c | 0xda, ..] => Framing::Zlib,
        _ => return Ok((bytes.to_vec(), Framing::Raw)),
    };
    let mut out = Vec::new();
    let res = match framing {
        Framing::Gzip => flate2::read::GzDecoder::new(bytes)
            .take(MAX_DOCUMENT_BYTES + 1)
            .read_to_end(&mut out),
        _ => flate2::read::ZlibDecoder::new(bytes)
            .take(MAX_DOCUMENT_BYTES + 1)
            .read_to_end(&mut out),
    };
    let name = if framing == Framing::Gzip {
        "gzip"
    } else {
        "zlib"
    };
    res.map_err(|e| format!("corrupt {name} stream: {e}"))?;
    if out.len() as u64 > MAX_DOCUMENT_BYTES {
        return Err(format!("{name} stream decompresses to more than 4 GiB"));
    }
    Ok((out, framing))
}

pub fn kind(v: &Value) -> &'static str {
    match v {
        Value::Nil => "null",
        Value::Boolean(_) => "a boolean",
        Value::Integer(_) => "an integer",
        Value::F32(_) | Value::F64(_) => "a float",
        Value::String(_) => "a string",
        Value::Binary(_) => "binary data",
        Value::Array(_) => "an array",
        Value::Map(_) => "a map",
        Value::Ext(..) => "an ext value",
    }
}

/// A map with the path that leads to it, for error messages.
#[derive(Clone, Copy)]
pub struct Obj<'a> {
    pub path: &'a str,
    pub m: &'a [(Value, Value)],
}

fn join(path: &str, key: &str) -> String {
    if path.is_empty() {
        key.to_string()
    } else {
        format!("{path}.{key}")
    }
}

fn as_num(v: &Value) -> Option<f64> {
    match v {
        Value::F32(x) => Some(*x as f64),
        Value::F64(x) => Some(*x),
        Value::Integer(i) => i.as_f64(),
        _ => None,
    }
}

fn as_int(v: &Value) -> Option<i64> {
    match v {
        Value::Integer(i) => i.as_i64(),
        Value::F32(_) | Value::F64(_) => {
            let x = as_num(v)?;
            (x.fract() == 0.0 && x.abs() < 9e15).then_some(x as i64)
        }
        _ => None,
    }
}

impl<'a> Obj<'a> {
    /// Last occurrence wins, as when nlohmann inserts duplicate keys.
    pub fn get(&self, key: &str) -> Option<&'a Value> {
        self.m
            .iter()
            .rev()
            .find(|(k, _)| k.as_str() == Some(key))
            .map(|(_, v)| v)
    }
    fn req(&self, key: &str) -> R<&'a Value> {
        self.get(key)
            .ok_or_else(|| format!("missing field {}", join(self.path, key)))
    }
    fn bad(&self, key: &str, want: &str, v: &Value) -> String {
        format!(
            "field {}: expected {want}, found {}",
            join(self.path, key),
            kind(v)
        )
    }
    pub fn f32(&self, key: &str) -> R<f32> {
        let v = self.req(key)?;
        as_num(v)
            .map(|x| x as f32)
            .ok_or_else(|| self.bad(key, "a number", v))
    }
    fn f32_or(&self, key: &str, d: f32) -> R<f32> {
        if self.get(key).is_some() {
            self.f32(key)
        } else {
            Ok(d)
        }
    }
    pub fn int(&self, key: &str, min: i64, max: i64) -> R<i64> {
        let v = self.req(key)?;
        let x = as_int(v).ok_or_else(|| self.bad(key, "an integer", v))?;
        if x < min || x > max {
            return Err(format!(
                "field {}: {x} is outside {min}..={max}",
                join(self.path, key)
            ));
        }
        Ok(x)
    }
    pub fn u32(&self, key: &str) -> R<u32> {
        self.int(key, 0, u32::MAX as i64).map(|x| x as u32)
    }
    fn u32_or(&self, key: &str, d: u32) -> R<u32> {
        if self.get(key).is_some() {
            self.u32(key)
        } else {
            Ok(d)
        }
    }
    fn bool_or(&self, key: &str, d: bool) -> R<bool> {
        match self.get(key) {
            None => Ok(d),
            Some(Value::Boolean(b)) => Ok(*b),
            Some(v) => Err(self.bad(key, "a boolean", v)),
        }
    }
    pub fn str(&self, key: &str) -> R<&'a str> {
        let v = self.req(key)?;
        v.as_str().ok_or_else(|| self.bad(key, "a string", v))
    }
    fn str_or(&self, key: &str, d: &'a str) -> R<&'a str> {
        if self.get(key).is_some() {
            self.str(key)
        } else {
            Ok(d)
        }
    }
    pub fn bin(&self, key: &str) -> R<&'a [u8]> {
        match self.req(key)? {
            Value::Binary(b) => Ok(b),
            v => Err(self.bad(key, "binary data", v)),
        }
    }
    pub fn arr(&self, key: &str) -> R<&'a [Value]> {
        match self.req(key)? {
            Value::Array(a) => Ok(a),
            v => Err(self.bad(key, "an array", v)),
        }
    }
    fn floats<const N: usize>(&self, key: &str) -> R<[f32; N]> {
        floats(self.req(key)?, &join(self.path, key))
    }
    fn floats_or<const N: usize>(&self, key: &str, d: [f32; N]) -> R<[f32; N]> {
        if self.get(key).is_some() {
            self.floats(key)
        } else {
            Ok(d)
        }
    }
    fn ints<const N: usize>(&self, key: &str) -> R<[i32; N]> {
        let p = join(self.path, key);
        let a = match self.req(key)? {
            Value::Array(a) if a.len() >= N => a,
            v => {
                return Err(format!(
                    "field {p}: expected {N} integers, found {}",
                    kind(v)
                ));
            }
        };
        let mut out = [0i32; N];
        for (o, v) in out.iter_mut().zip(a) {
            *o = as_int(v)
                .and_then(|x| i32::try_from(x).ok())
                .ok_or_else(|| format!("field {p}: expected integers, found {}", kind(v)))?;
        }
        Ok(out)
    }
    fn mat<const N: usize, const M: usize>(&self, key: &str) -> R<[[f32; N]; M]> {
        let p = join(self.path, key);
        let a = match self.req(key)? {
            Value::Array(a) if a.len() >= M => a,
            v => return Err(format!("field {p}: expected {M} rows, found {}", kind(v))),
        };
        let mut out = [[0f32; N]; M];
        for (r, v) in out.iter_mut().zip(a) {
            *r = floats(v, &p)?;
        }
        Ok(out)
    }
    pub fn obj(&self, key: &str, path: &'a str) -> R<Obj<'a>> {
        match self.req(key)? {
            Value::Map(m) => Ok(Obj { path, m }),
            v => Err(self.bad(key, "a map", v)),
        }
    }
    /// The map at `key` (named `path` in errors), or `None` where there is no `key`.
    fn opt_obj(&self, key: &str, path: &'a str) -> R<Option<Obj<'a>>> {
        match self.get(key) {
            None => Ok(None),
            Some(Value::Map(m)) => Ok(Some(Obj { path, m })),
            Some(v) => Err(self.bad(key, "a map", v)),
        }
    }
    fn aabb(&self, key: &str) -> R<Aabb> {
        let p = join(self.path, key);
        let o = self.obj(key, &p)?;
        Ok(Aabb {
            min: o.floats("min")?,
            max: o.floats("max")?,
        })
    }
}

fn floats<const N: usize>(v: &Value, path: &str) -> R<[f32; N]> {
    let a = match v {
        Value::Array(a) if a.len() >= N => a,
        v => {
            return Err(format!(
                "field {path}: expected {N} numbers, found {}",
                kind(v)
            ));
        }
    };
    let mut out = [0f32; N];
    for (o, v) in out.iter_mut().zip(a) {
        *o = as_num(v)
            .ok_or_else(|| format!("field {path}: expected numbers, found {}", kind(v)))?
            as f32;
    }
    Ok(out)
}

/// nlohmann refuses documents whose map keys are not strings; so do we.
fn check_string_keys(root: &Value) -> R<()> {
    let mut stack = vec![root];
    while let Some(v) = stack.pop() {
        match v {
            Value::Map(m) => {
                for (k, v) in m {
                    if !k.is_str() {
                        return Err(format!("a map key is {}, not a string", kind(k)));
                    }
                    stack.push(v);
                }
            }
            Value::Array(a) => stack.extend(a.iter()),
            _ => {}
        }
    }
    Ok(())
}

fn mlp_check(net: Obj, hidden: i64, name: &str) -> R<()> {
    let otype = net.str_or("otype", "")?;
    if !otype.eq_ignore_ascii_case("FullyFusedMLP") {
        return Err(format!(
            "{name} is '{otype}'; only FullyFusedMLP networks are supported"
        ));
    }
    let neurons = net.int("n_neurons", 0, i64::MAX)?;
    let layers = net.int("n_hidden_layers", 0, i64::MAX)?;
    if neurons != 64 || layers != hidden {
        return Err(format!(
            "{name} has {neurons} neurons × {layers} hidden layers; only 64 × {hidden} is supported"
        ));
    }
    let act = net.str_or("activation", "ReLU")?;
    let out = net.str_or("output_activation", "None")?;
    if !act.eq_ignore_ascii_case("ReLU") || !out.eq_ignore_ascii_case("None") {
        return Err(format!(
            "{name} uses activation '{act}' / output '{out}'; only ReLU / None is supported"
        ));
    }
    if name == "network" && net.get("n_output_dims").is_some() && net.u32("n_output_dims")? != 16 {
        return Err("density network with other than 16 outputs is not supported".into());
    }
    Ok(())
}

fn sh4_check(o: Obj) -> R<bool> {
    Ok(o.str_or("otype", "")?
        .eq_ignore_ascii_case("SphericalHarmonics")
        && o.get("degree").is_some()
        && o.u32("degree")? == 4
        && (o.get("n_dims_to_encode").is_none() || o.u32("n_dims_to_encode")? == 3))
}

fn dir_encoding_check(d: Obj) -> R<()> {
    let otype = d.str_or("otype", "")?;
    let ok = if otype.eq_ignore_ascii_case("Composite") {
        let nested = d.arr("nested")?;
        let maps: Vec<Obj> = nested
            .iter()
            .filter_map(|v| match v {
                Value::Map(m) => Some(Obj {
                    path: "dir_encoding.nested",
                    m,
                }),
                _ => None,
            })
            .collect();
        maps.len() == nested.len()
            && !maps.is_empty()
            && sh4_check(maps[0])?
            && maps[1..].iter().all(|m| {
                m.str_or("otype", "")
                    .map(|t| t.eq_ignore_ascii_case("Identity"))
                    .unwrap_or(false)
            })
    } else {
        sh4_check(d)?
    };
    if ok {
        Ok(())
    } else {
        Err(format!(
            "dir_encoding is '{otype}' in a form other than spherical harmonics of degree 4; unsupported"
        ))
    }
}

/// The hash-grid configuration a top-level config describes, with instant-ngp's defaults
/// (`reset_network`), refusing networks the engine does not implement.
pub fn config_from_value(top: &[(Value, Value)]) -> R<GridConfig> {
    let root = Obj { path: "", m: top };
    let enc = root.obj("encoding", "encoding")?;
    let otype = enc.str_or("otype", "OneBlob")?;
    let hash = otype.eq_ignore_ascii_case("HashGrid")
        || (otype.eq_ignore_ascii_case("Grid")
            && enc.str_or("type", "Hash")?.eq_ignore_ascii_case("Hash"));
    if !hash {
        return Err(format!(
            "encoding is '{otype}'; only the HashGrid encoding is supported"
        ));
    }
    let interp = enc.str_or("interpolation", "Linear")?;
    if !interp.eq_ignore_ascii_case("Linear") {
        return Err(format!(
            "hash grid uses '{interp}' interpolation; only Linear is supported"
        ));
    }
    let hash_fn = enc.str_or("hash", "CoherentPrime")?;
    if !hash_fn.eq_ignore_ascii_case("CoherentPrime") {
        return Err(format!(
            "hash grid uses the '{hash_fn}' hash; only CoherentPrime is supported"
        ));
    }
    let n_features = enc.u32_or("n_features_per_level", 2)?;
    let n_levels = match enc.get("n_features") {
        Some(_) if enc.u32("n_features")? > 0 => enc.u32("n_features")? / n_features.max(1),
        _ => enc.u32_or("n_levels", 16)?,
    };
    let log2_hashmap_size = enc.u32_or("log2_hashmap_size", 19)?;
    let mut base_resolution = enc.u32_or("base_resolution", 0)?;
    if base_resolution == 0 {
        base_resolution = 1 << (enc.u32_or("log2_hashmap_size", 15)?.min(93) / 3);
    }
    let grid = GridConfig {
        n_levels,
        n_features,
        log2_hashmap_size,
        base_resolution,
    };
    grid.validate().map_err(|e| format!("encoding: {e}"))?;
    mlp_check(root.obj("network", "network")?, 1, "network")?;
    mlp_check(root.obj("rgb_network", "rgb_network")?, 2, "rgb_network")?;
    dir_encoding_check(root.obj("dir_encoding", "dir_encoding")?)?;
    Ok(grid)
}

fn lens(v: Option<&Value>, path: &str) -> R<Lens> {
    let m = match v {
        None | Some(Value::Nil) => return Ok(Lens::Perspective),
        Some(Value::Map(m)) => Obj { path, m },
        Some(v) => return Err(format!("field {path}: expected a map, found {}", kind(v))),
    };
    Ok(if m.get("k1").is_some() {
        if m.bool_or("is_fisheye", false)? {
            Lens::OpenCvFisheye {
                k1: m.f32("k1")?,
                k2: m.f32("k2")?,
                k3: m.f32("k3")?,
                k4: m.f32("k4")?,
            }
        } else {
            Lens::OpenCv {
                k1: m.f32("k1")?,
                k2: m.f32("k2")?,
                p1: m.f32("p1")?,
                p2: m.f32("p2")?,
            }
        }
    } else if m.get("ftheta_p0").is_some() {
        Lens::FTheta {
            p: [
                m.f32("ftheta_p0")?,
                m.f32("ftheta_p1")?,
                m.f32("ftheta_p2")?,
                m.f32("ftheta_p3")?,
                m.f32("ftheta_p4")?,
            ],
            w: m.f32("w")?,
            h: m.f32("h")?,
        }
    } else if m.get("latlong").is_some() {
        Lens::LatLong
    } else if m.get("equirectangular").is_some() {
        Lens::Equirectangular
    } else if m.get("orthographic").is_some() {
        Lens::Orthographic
    } else {
        Lens::Perspective
    })
}

/// `from_json(NerfDataset)`, reading per-image metadata as `to_json` writes it.
fn dataset(d: Obj) -> R<SnapshotDataset> {
    let n = d.int("n_images", 0, u32::MAX as i64)? as usize;
    // Sizes are checked against the arrays before anything is allocated per image.
    let xforms = d
        .arr("xforms")
        .or_else(|e| if n == 0 { Ok(&[][..]) } else { Err(e) })?;
    if xforms.len() < n {
        return Err(format!(
            "field snapshot.nerf.dataset.xforms: {} entries for {n} images",
            xforms.len()
        ));
    }
    let meta = match d.get("metadata") {
        Some(_) => Some(d.arr("metadata")?),
        None => None,
    };
    if let Some(m) = meta
        && m.len() < n
    {
        return Err(format!(
            "field snapshot.nerf.dataset.metadata: {} entries for {n} images",
            m.len()
        ));
    }
    let paths = match d.get("paths") {
        None => vec![String::new(); n],
        Some(_) => d
            .arr("paths")?
            .iter()
            .map(|p| {
                p.as_str().map(str::to_string).ok_or_else(|| {
                    "field snapshot.nerf.dataset.paths: expected strings".to_string()
                })
            })
            .collect::<R<Vec<_>>>()?,
    };
    let mut images = Vec::with_capacity(n);
    for i in 0..n {
        let xp = format!("snapshot.nerf.dataset.xforms[{i}]");
        let x = match &xforms[i] {
            Value::Map(m) => Obj { path: &xp, m },
            v => return Err(format!("field {xp}: expected a map, found {}", kind(v))),
        };
        let mut im = DatasetImage::new([0, 0], [1000.0, 1000.0], x.mat("start")?);
        im.xform_end = x.mat("end")?;
        if let Some(meta) = meta {
            let mp = format!("snapshot.nerf.dataset.metadata[{i}]");
            let m = match &meta[i] {
                Value::Map(m) => Obj { path: &mp, m },
                v => return Err(format!("field {mp}: expected a map, found {}", kind(v))),
            };
            im.resolution = m.ints("resolution")?;
            im.focal_length = m.floats("focal_length")?;
            im.principal_point = m.floats("principal_point")?;
            im.rolling_shutter = m.floats_or("rolling_shutter", [0.0; 4])?;
            im.lens = lens(m.get("lens"), &format!("{mp}.lens"))?;
        }
        images.push(im);
    }
    Ok(SnapshotDataset {
        paths,
        images,
        render_aabb: d.aabb("render_aabb")?,
        render_aabb_to_local: if d.get("render_aabb_to_local").is_some() {
            d.mat("render_aabb_to_local")?
        } else {
            IDENTITY3
        },
        up: d.floats("up")?,
        offset: d.floats("offset")?,
        envmap_resolution: d.ints("envmap_resolution")?,
        scale: d.f32("scale")?,
        aabb_scale: d.int("aabb_scale", i32::MIN as i64, i32::MAX as i64)? as i32,
        from_mitsuba: d.bool_or("from_mitsuba", false)?,
        is_hdr: d.bool_or("is_hdr", false)?,
        wants_importance_sampling: d.bool_or("wants_importance_sampling", true)?,
        n_extra_learnable_dims: d.u32_or("n_extra_learnable_dims", 0)?,
    })
}

fn camera(c: Obj) -> R<SnapshotCamera> {
    let d = SnapshotCamera::default();
    Ok(SnapshotCamera {
        matrix: if c.get("matrix").is_some() {
            c.mat("matrix")?
        } else {
            d.matrix
        },
        fov_axis: c.u32_or("fov_axis", d.fov_axis)?,
        relative_focal_length: c.floats_or("relative_focal_length", d.relative_focal_length)?,
        screen_center: c.floats_or("screen_center", d.screen_center)?,
        zoom: c.f32_or("zoom", d.zoom)?,
        scale: c.f32_or("scale", d.scale)?,
        aperture_size: c.f32_or("aperture_size", d.aperture_size)?,
        autofocus: c.bool_or("autofocus", d.autofocus)?,
        autofocus_target: c.floats_or("autofocus_target", d.autofocus_target)?,
        autofocus_depth: c.f32_or("autofocus_depth", d.autofocus_depth)?,
    })
}

fn decode_params(bin: &[u8], elem: usize) -> Vec<f32> {
    let mut out = crate::pages::with_capacity(bin.len() / elem.max(1));
    if elem == 2 {
        out.extend(
            bin.chunks_exact(2)
                .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()),
        );
    } else {
        out.extend(
            bin.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
        );
    }
    out
}

pub fn from_msgpack(raw: &[u8]) -> R<Snapshot> {
    let doc = decode(raw)?;
    let top = match &doc {
        Value::Map(m) => m,
        v => {
            return Err(format!(
                "not an instant-ngp snapshot: the msgpack document is {}, not a map",
                kind(v)
            ));
        }
    };
    check_string_keys(&doc)?;
    let root = Obj { path: "", m: top };
    let snap = root.opt_obj("snapshot", "snapshot")?.ok_or_else(|| {
        "not an instant-ngp snapshot: no 'snapshot' field (a network config without weights?)"
            .to_string()
    })?;
    check_version_and_mode(snap)?;
    let nerf = snap.obj("nerf", "snapshot.nerf")?;

    let grid = config_from_value(top)?;
    let aabb_scale = nerf_aabb_scale(nerf)?;
    let ds = nerf_dataset(nerf)?;
    check_per_level_scale(root, &grid, aabb_scale)?;
    let config = ModelConfig { grid, aabb_scale };
    let (pbin, elem) = params_binary(snap, config)?;
    let (gbin, exact_density) = density_grid(snap, aabb_scale)?;
    let rgb = nerf.obj("rgb", "snapshot.nerf.rgb")?;
    let view = view(snap, aabb_scale)?;
    let cam = match snap.opt_obj("camera", "snapshot.camera")? {
        Some(c) => camera(c)?,
        None => SnapshotCamera::default(),
    };
    let preserved = Preserved {
        network_config: Some(Value::Map(
            top.iter()
                .filter(|(k, _)| k.as_str() != Some("snapshot"))
                .cloned()
                .collect(),
        )),
        optimizer: snap.get("optimizer").cloned(),
        cam_pos_offset: nerf.get("cam_pos_offset").cloned(),
        cam_rot_offset: nerf.get("cam_rot_offset").cloned(),
        extra_dims_opt: nerf.get("extra_dims_opt").cloned(),
        run_state: snap.get("stegongp_run_state").cloned(),
    };
    Ok(Snapshot {
        config,
        params: decode_params(pbin, elem),
        exact: elem == 4 && exact_density.is_some(),
        density_grid: exact_density.unwrap_or_else(|| decode_params(gbin, 2)),
        training_step: snap.u32("training_step")?,
        loss: snap.f32("loss")?,
        dataset: ds,
        rays_per_batch: rgb.u32("rays_per_batch")?,
        measured_batch_size: rgb.u32("measured_batch_size")?,
        measured_batch_size_before_compaction: rgb.u32("measured_batch_size_before_compaction")?,
        camera: cam,
        view,
        preserved,
    })
}

/// `snapshot.version` (0 where it is missing) must be 1, and `snapshot.mode` NeRF.
fn check_version_and_mode(snap: Obj) -> R<()> {
    let version = match snap.get("version") {
        Some(_) => snap.int("version", i64::MIN, i64::MAX)?,
        None => 0,
    };
    if version < SNAPSHOT_VERSION as i64 {
        return Err(format!(
            "snapshot format version {version} is older than 1 and cannot be loaded (nor can the reference load it)"
        ));
    }
    if version > SNAPSHOT_VERSION as i64 {
        return Err(format!(
            "snapshot format version {version} is newer than the supported version 1"
        ));
    }
    let mode = snap.str_or("mode", "nerf")?;
    if mode != "nerf" {
        return Err(format!(
            "the file holds an instant-ngp '{mode}' model; only NeRF snapshots are supported"
        ));
    }
    Ok(())
}

/// `snapshot.nerf.aabb_scale`: 1 where it is missing, else a power of two ≤ 128.
fn nerf_aabb_scale(nerf: Obj) -> R<u32> {
    let aabb_scale = nerf.int("aabb_scale", 1, i32::MAX as i64).or_else(|e| {
        if nerf.get("aabb_scale").is_none() {
            Ok(1)
        } else {
            Err(e)
        }
    })? as u32;
    if !aabb_scale.is_power_of_two() || aabb_scale > MAX_AABB_SCALE {
        return Err(format!(
            "field snapshot.nerf.aabb_scale: {aabb_scale} is not a power of two ≤ 128"
        ));
    }
    Ok(aabb_scale)
}

/// `snapshot.nerf.dataset`, if there is one, without latent dimensions.
fn nerf_dataset(nerf: Obj) -> R<Option<SnapshotDataset>> {
    let ds = match nerf.opt_obj("dataset", "snapshot.nerf.dataset")? {
        Some(d) => Some(dataset(d)?),
        None => None,
    };
    if let Some(d) = &ds
        && d.n_extra_learnable_dims > 0
    {
        return Err(format!(
            "the model has {} extra learnable (latent) dimensions per image; unsupported",
            d.n_extra_learnable_dims
        ));
    }
    Ok(ds)
}

/// instant-ngp only derives b when the config leaves it out; a stored one must agree.
fn check_per_level_scale(root: Obj, grid: &GridConfig, aabb_scale: u32) -> R<()> {
    let enc = root.obj("encoding", "encoding")?;
    if enc.get("per_level_scale").is_some() {
        let stored = enc.f32("per_level_scale")?;
        let derived = per_level_scale(grid, aabb_scale);
        if stored > 0.0 && (stored - derived).abs() > 1e-6 * derived {
            return Err(format!(
                "encoding.per_level_scale is {stored}, not the {derived} instant-ngp derives for aabb_scale {aabb_scale}; unsupported"
            ));
        }
    }
    Ok(())
}

/// The weights' bytes and the bytes of one weight (2: fp16, 4: f32), checked against the
/// parameter count of `config`'s network.
fn params_binary<'a>(snap: Obj<'a>, config: ModelConfig) -> R<(&'a [u8], usize)> {
    let ModelConfig { grid, aabb_scale } = config;
    let layout = NerfLayout::new(config).map_err(|e| e.to_string())?;
    let n_params = snap.int("n_params", 0, i64::MAX)? as usize;
    if n_params != layout.n_params {
        return Err(format!(
            "field snapshot.n_params: {n_params}, but a {}×{} hash grid with T=2^{}, base resolution {} at aabb_scale {aabb_scale} and the NeRF MLPs have {} parameters",
            grid.n_levels,
            grid.n_features,
            grid.log2_hashmap_size,
            grid.base_resolution,
            layout.n_params
        ));
    }
    let ptype = snap.str_or("params_type", "__half")?;
    let elem = match ptype {
        "__half" => 2,
        "float" => 4,
        t => {
            return Err(format!(
                "field snapshot.params_type: '{t}' (only __half and float exist)"
            ));
        }
    };
    let pbin = snap.bin("params_binary")?;
    if pbin.len() != n_params * elem {
        return Err(format!(
            "field snapshot.params_binary: {} bytes, expected {n_params} × {elem}",
            pbin.len()
        ));
    }
    Ok((pbin, elem))
}

/// The occupancy grid's fp16 bytes (empty: never populated) and, where the file has them,
/// its exact f32 values.
fn density_grid<'a>(snap: Obj<'a>, aabb_scale: u32) -> R<(&'a [u8], Option<Vec<f32>>)> {
    let gsize = snap.int("density_grid_size", 0, i64::MAX)?;
    if gsize != DENSITY_GRID_SIZE as i64 {
        return Err(format!(
            "field snapshot.density_grid_size: {gsize}, only 128 is supported"
        ));
    }
    let gbin = snap.bin("density_grid_binary")?;
    let cells = DENSITY_GRID_CELLS * n_cascades(aabb_scale);
    if !gbin.is_empty() && gbin.len() != cells * 2 {
        return Err(format!(
            "field snapshot.density_grid_binary: {} bytes, expected {cells} fp16 cells ({} cascades of 128³) = {} bytes",
            gbin.len(),
            n_cascades(aabb_scale),
            cells * 2
        ));
    }
    let exact_density = match snap.get(super::write::EXACT_DENSITY_KEY) {
        None => None,
        Some(_) => {
            let b = snap.bin(super::write::EXACT_DENSITY_KEY)?;
            if b.len() != gbin.len() * 2 {
                return Err(format!(
                    "field snapshot.{}: {} bytes, expected twice density_grid_binary's {}",
                    super::write::EXACT_DENSITY_KEY,
                    b.len(),
                    gbin.len()
                ));
            }
            Some(decode_params(b, 4))
        }
    };
    Ok((gbin, exact_density))
}

/// The render settings, with [`SnapshotView::for_scale`]'s where the file has none.
fn view(snap: Obj, aabb_scale: u32) -> R<SnapshotView> {
    let dv = SnapshotView::for_scale(aabb_scale);
    Ok(SnapshotView {
        aabb: if snap.get("aabb").is_some() {
            snap.aabb("aabb")?
        } else {
            dv.aabb
        },
        bounding_radius: snap.f32_or("bounding_radius", dv.bounding_radius)?,
        render_aabb: if snap.get("render_aabb").is_some() {
            snap.aabb("render_aabb")?
        } else {
            dv.render_aabb
        },
        render_aabb_to_local: if snap.get("render_aabb_to_local").is_some() {
            snap.mat("render_aabb_to_local")?
        } else {
            IDENTITY3
        },
        up_dir: snap.floats_or("up_dir", dv.up_dir)?,
        sun_dir: snap.floats_or("sun_dir", dv.sun_dir)?,
        exposure: snap.f32_or("exposure", dv.exposure)?,
        background_color: snap.floats_or("background_color", dv.background_color)?,
    })
}
