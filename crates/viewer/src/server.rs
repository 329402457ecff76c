//! The local web viewer's server: one page, frames rendered here on the chosen device and
//! sent as PNG, a key entered in the page held only in this process's memory.
//!
//! Security, as Jupyter's: every request carries a random token (refused without it), the
//! Host header must name this server (so another site's page, even through DNS rebinding,
//! cannot drive it), the page loads nothing from another origin (a content security policy
//! says so to the browser), and the default address is loopback.

use crate::frame::Rgb8;
use crate::path::{CameraPath, NerfFrame, PathCamera, SceneRig, nerfstudio_json};
use backend::Device;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::render::image::{RenderOptions, VIEWING_MIN_TRANSMITTANCE};
use serde_json::{Value, json};
use std::io::Read;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Instant;
use stego::{DenseMode, Key, OpenedScene, open_scene_on};
use tiny_http::{Header, Method, Request, Response, Server};

use crate::gate::{self, MAX_BODY, SocketDir};
/// Largest frame the page may ask for, in pixels.
const MAX_PIXELS: u32 = 4096 * 4096;

/// What the viewer shows and how.
pub struct ViewerOptions {
    /// Full-resolution frame size.
    pub width: u32,
    pub height: u32,
    /// Interactive frames are at most this fraction of the full size on each side.
    pub interactive_scale: f32,
    /// The render time interactive frames aim at: the page shrinks or grows them (from
    /// 1/16 of the full size on a side up to `interactive_scale`) after each one, as
    /// instant-ngp's dynamic resolution holds a frame rate. 0 keeps them at
    /// `interactive_scale`.
    pub frame_seconds: f32,
    pub background: [f32; 3],
    /// Transmittance a full frame's rays stop at; interactive frames stop at
    /// [`VIEWING_MIN_TRANSMITTANCE`] at least.
    pub min_transmittance: f32,
    /// Where the record button writes its nerfstudio camera path.
    pub record: PathBuf,
    /// Seed of a key holder's grid rebuild.
    pub seed: u64,
}

/// The scene's cameras and frame, for the page's start view and its camera list.
pub struct ViewerRig {
    pub cameras: Vec<PathCamera>,
    pub rig: SceneRig,
    pub frame: NerfFrame,
}

/// A running viewer: the bound server and its token.
pub struct Viewer {
    server: Server,
    token: String,
    nonce: String,
    hosts: Vec<String>,
    /// The port the front door listens on.
    port: u16,
    /// Where the server's socket lives; removed with the viewer.
    _socket_dir: SocketDir,
}

fn random_hex(bytes: usize) -> Result<String> {
    let mut b = vec![0u8; bytes];
    getrandom::fill(&mut b)
        .map_err(|e| Error::format("token", format!("no OS randomness: {e}")))?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

impl Viewer {
    /// Binds `addr` (port 0: any free port).
    pub fn bind(addr: SocketAddr) -> Result<Self> {
        let cannot = |e: &dyn std::fmt::Display| {
            Error::format(addr.to_string(), format!("cannot listen: {e}"))
        };
        // Requests come in through the front door (`gate`), which bounds them before the
        // HTTP server, reachable only through a socket in a private folder, sees them.
        let front = std::net::TcpListener::bind(addr).map_err(|e| cannot(&e))?;
        let port = front.local_addr().map_err(|e| cannot(&e))?.port();
        let socket_dir = SocketDir::new(&random_hex(12)?).map_err(|e| cannot(&e))?;
        let server = Server::http_unix(&socket_dir.socket()).map_err(|e| cannot(&e))?;
        gate::spawn(front, socket_dir.socket(), gate::Waits::default());
        let mut viewer = Viewer {
            server,
            token: random_hex(24)?,
            nonce: random_hex(16)?,
            hosts: Vec::new(),
            port,
            _socket_dir: socket_dir,
        };
        viewer.hosts = ["127.0.0.1", "localhost", "[::1]"]
            .iter()
            .map(|h| format!("{h}:{port}"))
            .collect();
        if !addr.ip().is_loopback() && !addr.ip().is_unspecified() {
            viewer
                .hosts
                .push(SocketAddr::new(addr.ip(), port).to_string());
        }
        Ok(viewer)
    }

    /// Also accept requests that name the server `host` (an address or name it is reached by
    /// when bound beyond loopback).
    pub fn allow_host(&mut self, host: &str) {
        self.hosts.push(host.to_string());
    }

    pub fn port(&self) -> u16 {
        self.port
    }

    /// The URL to open, token included.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}/?token={}", self.port(), self.token)
    }

    /// Serves until the process ends; `log` receives one line per notable event (never key
    /// material).
    pub fn serve(
        &self,
        device: &Device,
        model: &Model,
        rig: &ViewerRig,
        opts: &ViewerOptions,
        mut log: impl FnMut(&str),
    ) -> Result<()> {
        let mut recorded = load_recording(&opts.record, &rig.frame)?;
        let mut current = Current {
            scene: open_scene_on(device, model, None, false, opts.seed)?,
            label: "cover",
        };
        loop {
            let mut renderer = current.scene.renderer(device, model)?;
            let next = loop {
                let req = self
                    .server
                    .recv()
                    .map_err(|e| Error::format("viewer", format!("accepting a request: {e}")))?;
                let ctx = Ctx {
                    device,
                    model,
                    rig,
                    opts,
                    scene_label: current.label,
                };
                match self.handle(req, &ctx, renderer.as_mut(), &mut recorded, &mut log) {
                    Some(next) => break next,
                    None => continue,
                }
            };
            drop(renderer);
            current = next;
        }
    }

    fn allowed(&self, req: &Request) -> std::result::Result<(), (u16, &'static str)> {
        let host = req
            .headers()
            .iter()
            .find(|h| h.field.equiv("Host"))
            .map(|h| h.value.as_str().to_ascii_lowercase());
        match host {
            Some(h) if self.hosts.iter().any(|a| a.eq_ignore_ascii_case(&h)) => {}
            _ => return Err((403, "this server answers only requests addressed to it")),
        }
        let token = query(req.url())
            .find(|(k, _)| *k == "token")
            .map(|(_, v)| v);
        match token {
            Some(t) if constant_time_eq(t.as_bytes(), self.token.as_bytes()) => Ok(()),
            _ => Err((
                403,
                "missing or wrong token: open the URL the viewer printed",
            )),
        }
    }

    /// Answers one request; `Some(scene)` when the request switched the scene.
    fn handle(
        &self,
        mut req: Request,
        ctx: &Ctx,
        renderer: &mut dyn backend::RenderBackend,
        recorded: &mut CameraPath,
        log: &mut impl FnMut(&str),
    ) -> Option<Current> {
        if let Err((code, msg)) = self.allowed(&req) {
            respond(req, error_response(code, msg));
            return None;
        }
        let route = req.url().split('?').next().unwrap_or("").to_string();
        let method = req.method().clone();
        match (method, route.as_str()) {
            (Method::Get, "/") => {
                let page = PAGE.replace("{{NONCE}}", &self.nonce);
                let r = Response::from_data(page.into_bytes())
                    .with_header(header("Content-Type", "text/html; charset=utf-8"));
                respond(req, self.secured(r));
                None
            }
            (Method::Get, "/info") => {
                let r = json_response(200, &info(ctx));
                respond(req, self.secured(r));
                None
            }
            (Method::Get, "/frame") => {
                let r = match frame(&req, ctx, renderer) {
                    Ok((png, secs, (w, h))) => Response::from_data(png)
                        .with_header(header("Content-Type", "image/png"))
                        .with_header(header("X-Render-Seconds", &format!("{secs:.4}")))
                        .with_header(header("X-Frame-Size", &format!("{w}x{h}")))
                        .with_header(header("X-Scene", ctx.scene_label)),
                    Err(msg) => error_response(400, &msg),
                };
                respond(req, self.secured(r));
                None
            }
            (Method::Post, "/key") => {
                let body = match read_body(&mut req) {
                    Ok(b) => b,
                    Err(msg) => {
                        respond(req, self.secured(error_response(400, &msg)));
                        return None;
                    }
                };
                let t0 = Instant::now();
                match open_key(&body, ctx) {
                    Ok(scene) => {
                        let secs = t0.elapsed().as_secs_f64();
                        log(&format!(
                            "hidden scene opened from a key entered in the page ({secs:.1} s)"
                        ));
                        let r = json_response(200, &json!({"scene": "key", "seconds": secs}));
                        respond(req, self.secured(r));
                        Some(Current {
                            scene,
                            label: "key",
                        })
                    }
                    Err(msg) => {
                        respond(req, self.secured(error_response(400, &msg)));
                        None
                    }
                }
            }
            (Method::Post, "/forget") => {
                let scene = open_scene_on(ctx.device, ctx.model, None, false, ctx.opts.seed);
                match scene {
                    Ok(scene) => {
                        log("key forgotten: showing the cover");
                        respond(
                            req,
                            self.secured(json_response(200, &json!({"scene": "cover"}))),
                        );
                        Some(Current {
                            scene,
                            label: "cover",
                        })
                    }
                    Err(e) => {
                        respond(req, self.secured(error_response(500, &e.to_string())));
                        None
                    }
                }
            }
            (Method::Post, "/record") => {
                let r = match read_body(&mut req).and_then(|b| record(&b, ctx, recorded)) {
                    Ok(n) => {
                        log(&format!(
                            "recorded camera {n} into {}",
                            ctx.opts.record.display()
                        ));
                        json_response(200, &json!({"count": n, "file": ctx.opts.record}))
                    }
                    Err(msg) => error_response(400, &msg),
                };
                respond(req, self.secured(r));
                None
            }
            (Method::Get, _) | (Method::Post, _) => {
                respond(req, self.secured(error_response(404, "no such page")));
                None
            }
            _ => {
                respond(req, self.secured(error_response(405, "method not allowed")));
                None
            }
        }
    }

    fn secured<R: Read>(&self, r: Response<R>) -> Response<R> {
        let csp = format!(
            "default-src 'none'; script-src 'nonce-{}'; style-src 'unsafe-inline'; img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
            self.nonce
        );
        r.with_header(header("Content-Security-Policy", &csp))
            .with_header(header("X-Content-Type-Options", "nosniff"))
            .with_header(header("Referrer-Policy", "no-referrer"))
            .with_header(header("Cache-Control", "no-store"))
            .with_header(header("X-Frame-Options", "DENY"))
    }
}

struct Current {
    scene: OpenedScene,
    label: &'static str,
}

struct Ctx<'a> {
    device: &'a Device,
    model: &'a Model,
    rig: &'a ViewerRig,
    opts: &'a ViewerOptions,
    scene_label: &'static str,
}

const PAGE: &str = include_str!("viewer.html");

fn header(k: &str, v: &str) -> Header {
    Header::from_bytes(k.as_bytes(), v.as_bytes()).expect("ASCII header")
}

fn json_response(code: u16, v: &Value) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_data(v.to_string().into_bytes())
        .with_status_code(code)
        .with_header(header("Content-Type", "application/json"))
}

fn error_response(code: u16, msg: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    json_response(code, &json!({"error": msg}))
}

fn respond<R: Read>(req: Request, r: Response<R>) {
    // A page that went away mid-answer is no error of ours.
    let _ = req.respond(r);
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// `key=value` pairs of a URL's query (no percent-decoding: the page sends plain numbers and
/// hex).
fn query(url: &str) -> impl Iterator<Item = (&str, &str)> {
    url.split_once('?')
        .map_or("", |(_, q)| q)
        .split('&')
        .filter_map(|kv| kv.split_once('='))
}

fn read_body(req: &mut Request) -> std::result::Result<Vec<u8>, String> {
    if req.body_length().is_some_and(|n| n as u64 > MAX_BODY) {
        return Err(format!("request body larger than {MAX_BODY} bytes"));
    }
    let mut body = Vec::new();
    req.as_reader()
        .take(MAX_BODY + 1)
        .read_to_end(&mut body)
        .map_err(|e| format!("reading the request: {e}"))?;
    if body.len() as u64 > MAX_BODY {
        return Err(format!("request body larger than {MAX_BODY} bytes"));
    }
    Ok(body)
}

fn pose_json(c: &PathCamera) -> Value {
    json!({"c2w": c.c2w.iter().flatten().collect::<Vec<_>>(), "fov": c.fov_y_deg})
}

fn info(ctx: &Ctx) -> Value {
    let r = &ctx.rig.rig;
    json!({
        "device": ctx.device.report(),
        "width": ctx.opts.width,
        "height": ctx.opts.height,
        "interactive_scale": ctx.opts.interactive_scale,
        "frame_seconds": ctx.opts.frame_seconds,
        "scene": ctx.scene_label,
        "rig": {
            "centre": r.centre, "up": r.up, "distance": r.distance,
            "elevation": r.elevation, "azimuth": r.azimuth, "fov": r.fov_y_deg,
        },
        "start": pose_json(&r.orbit(1)[0]),
        "cameras": ctx.rig.cameras.iter().map(pose_json).collect::<Vec<_>>(),
        "record": ctx.opts.record,
    })
}

fn parse_pose(c2w: &[f32], fov: f32) -> std::result::Result<PathCamera, String> {
    if c2w.len() != 12 || c2w.iter().any(|x| !x.is_finite()) {
        return Err("c2w: expected 12 finite numbers (3 rows of 4)".into());
    }
    if !(fov > 0.0 && fov < 180.0) {
        return Err(format!("fov: {fov} is not in (0, 180) degrees"));
    }
    let m = [
        [c2w[0], c2w[1], c2w[2], c2w[3]],
        [c2w[4], c2w[5], c2w[6], c2w[7]],
        [c2w[8], c2w[9], c2w[10], c2w[11]],
    ];
    Ok(PathCamera {
        c2w: m,
        fov_y_deg: fov,
    })
}

/// A frame's PNG, its render time and size.
type Rendered = (Vec<u8>, f64, (u32, u32));

fn frame(
    req: &Request,
    ctx: &Ctx,
    renderer: &mut dyn backend::RenderBackend,
) -> std::result::Result<Rendered, String> {
    let (mut c2w, mut fov, mut w, mut h, mut fast) = (Vec::new(), f32::NAN, 0u32, 0u32, false);
    for (k, v) in query(req.url()) {
        match k {
            "c2w" => {
                c2w = v
                    .split(',')
                    .take(13)
                    .map(|x| {
                        x.parse::<f32>()
                            .map_err(|_| format!("c2w: {x:?} is not a number"))
                    })
                    .collect::<std::result::Result<_, _>>()?
            }
            "fov" => {
                fov = v
                    .parse()
                    .map_err(|_| format!("fov: {v:?} is not a number"))?
            }
            "w" => {
                w = v
                    .parse()
                    .map_err(|_| format!("w: {v:?} is not a pixel count"))?
            }
            "h" => {
                h = v
                    .parse()
                    .map_err(|_| format!("h: {v:?} is not a pixel count"))?
            }
            "fast" => fast = v == "1",
            _ => {}
        }
    }
    let pose = parse_pose(&c2w, fov)?;
    // The page asks for the full size or less; more would only let a request hold the
    // renderer and its memory for minutes.
    let most = (ctx.opts.width as u64 * ctx.opts.height as u64).min(MAX_PIXELS as u64);
    if w == 0 || h == 0 || w as u64 * h as u64 > most {
        return Err(format!(
            "{w}x{h}: not a frame size this viewer renders (at most {}x{} pixels)",
            ctx.opts.width, ctx.opts.height
        ));
    }
    let opts = RenderOptions {
        background: ctx.opts.background,
        min_transmittance: if fast {
            ctx.opts.min_transmittance.max(VIEWING_MIN_TRANSMITTANCE)
        } else {
            ctx.opts.min_transmittance
        },
        ..Default::default()
    };
    let t0 = Instant::now();
    let img = renderer
        .render(&pose.camera(w, h), &opts)
        .map_err(|e| format!("rendering: {e}"))?;
    let secs = t0.elapsed().as_secs_f64();
    Ok((
        Rgb8::from_floats(img.width, img.height, &img.rgb).png(),
        secs,
        (w, h),
    ))
}

fn field<'a>(v: &'a Value, k: &str) -> Option<&'a Value> {
    v.get(k).filter(|x| !x.is_null())
}

/// The scene of a key entered in the page: a key file's text, or a passphrase and salt.
fn open_key(body: &[u8], ctx: &Ctx) -> std::result::Result<OpenedScene, String> {
    let v: Value = serde_json::from_slice(body).map_err(|e| format!("not JSON: {e}"))?;
    let stealth = field(&v, "stealth")
        .map(|s| s.as_bool().ok_or("stealth: expected true or false"))
        .transpose()?
        .unwrap_or(false);
    let robust = field(&v, "robust")
        .map(|s| s.as_bool().ok_or("robust: expected true or false"))
        .transpose()?
        .unwrap_or(false);
    let key: Key = if let Some(text) = field(&v, "key_file") {
        let text = text
            .as_str()
            .ok_or("key_file: expected the key file's text")?;
        stego::parse_key(Path::new("the key file given in the page"), text)
            .map_err(|e| e.to_string())?
    } else if let Some(pass) = field(&v, "passphrase") {
        let pass = pass.as_str().ok_or("passphrase: expected text")?;
        let salt = field(&v, "salt")
            .and_then(Value::as_str)
            .filter(|s| !s.is_empty())
            .ok_or("salt: the salt keygen printed is needed with a passphrase")?;
        let m = field(&v, "m")
            .map_or(Some(1), Value::as_u64)
            .ok_or("m: expected a whole number")? as usize;
        if !(1..=ctx.model.net.layout.grid.config.n_levels as usize).contains(&m) {
            return Err(format!(
                "m: {m} is not between 1 and the model's level count"
            ));
        }
        let dense = match field(&v, "dense") {
            None => DenseMode::Permute,
            Some(d) => d
                .as_str()
                .and_then(DenseMode::parse)
                .ok_or("dense: expected permute or hash")?,
        };
        let scene_box = field(&v, "aabb_scale")
            .map_or(Some(1), Value::as_u64)
            .ok_or("aabb_scale: expected a power of two")?;
        stego::derive_prf_from_passphrase(pass, salt, m)
            .and_then(|k| {
                k.with_dense(dense)
                    .with_scene_box(Some(scene_box.min(1 << 20) as u32))
            })
            .map_err(|e| e.to_string())?
    } else {
        return Err("expected key_file (a key file's text) or passphrase and salt".into());
    };
    key.validate_for(&ctx.model.net.layout.grid)
        .map_err(|e| format!("the key does not fit this model: {e}"))?;
    // A key file of a robust model records it; a passphrase says it with the box.
    let robust = robust || key.robust();
    let key = key.with_robust(robust);
    open_scene_on(ctx.device, ctx.model, Some(&key), stealth, ctx.opts.seed)
        .map_err(|e| e.to_string())
}

fn load_recording(path: &Path, frame: &NerfFrame) -> Result<CameraPath> {
    if path.exists() {
        // Recording goes on where an earlier session stopped, after the file's cameras.
        crate::path::read_path(path, None, frame)
    } else {
        Ok(CameraPath {
            cameras: Vec::new(),
            fps: crate::path::DEFAULT_FPS,
            size: None,
        })
    }
}

fn record(body: &[u8], ctx: &Ctx, recorded: &mut CameraPath) -> std::result::Result<usize, String> {
    let v: Value = serde_json::from_slice(body).map_err(|e| format!("not JSON: {e}"))?;
    let c2w: Vec<f32> = field(&v, "c2w")
        .and_then(Value::as_array)
        .ok_or("c2w: expected 12 numbers")?
        .iter()
        .take(13)
        .map(|x| x.as_f64().map(|f| f as f32).ok_or("c2w: expected numbers"))
        .collect::<std::result::Result<_, _>>()?;
    let fov = field(&v, "fov")
        .and_then(Value::as_f64)
        .ok_or("fov: expected a number")? as f32;
    let pose = parse_pose(&c2w, fov)?;
    if recorded.cameras.len() >= crate::path::MAX_FRAMES {
        return Err("the camera path is full".into());
    }
    recorded.cameras.push(pose);
    let text =
        nerfstudio_json(recorded, ctx.opts.width, ctx.opts.height, &ctx.rig.frame).to_string();
    if let Err(e) = ngp::util::write_atomic(&ctx.opts.record, text.as_bytes()) {
        recorded.cameras.pop();
        return Err(e.to_string());
    }
    Ok(recorded.cameras.len())
}
