//! The viewer's requests as a remote page (or anyone on the machine) can send them: raw
//! HTTP written to a live viewer serving a tiny model on loopback. A case is one request;
//! after it, a well-formed `/info` must still be answered, so a request that kills, hangs
//! or wedges the server is a finding even though its panic happens on the server's thread.

use crate::seeds::{self, Case};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::OnceLock;
use std::time::Duration;

struct Live {
    port: u16,
    token: String,
}

static LIVE: OnceLock<Result<Live, String>> = OnceLock::new();

/// Frame size of the fuzzed viewer: small, so a frame request renders in milliseconds.
const SIZE: (u32, u32) = (32, 24);

fn start() -> Result<Live, String> {
    let dir = std::env::temp_dir().join(format!("stegongp-fuzz-viewer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let model_path = dir.join("model.msgpack");
    let case = &seeds::snapshots()[0];
    std::fs::write(&model_path, &case[0].1).map_err(|e| e.to_string())?;
    let model = ngp::model::Model::load(&model_path).map_err(|e| e.to_string())?;
    let viewer = viewer::server::Viewer::bind("127.0.0.1:0".parse().expect("an address"))
        .map_err(|e| e.to_string())?;
    let url = viewer.url();
    let token = url
        .split("token=")
        .nth(1)
        .ok_or("the viewer's URL has no token")?
        .to_string();
    let port = viewer.port();
    let record = dir.join("recorded.json");
    std::thread::spawn(move || {
        let model: &'static ngp::model::Model = Box::leak(Box::new(model));
        let device: &'static backend::Device = Box::leak(Box::default());
        let cameras = viewer::path::model_cameras(model);
        let rig = viewer::server::ViewerRig {
            rig: viewer::path::SceneRig::of(&cameras, [0.5; 3])
                .unwrap_or_else(viewer::path::SceneRig::default_object),
            cameras,
            frame: viewer::path::NerfFrame::of_model(model),
        };
        let opts = viewer::server::ViewerOptions {
            width: SIZE.0,
            height: SIZE.1,
            interactive_scale: 0.5,
            frame_seconds: 0.25,
            background: [1.0; 3],
            min_transmittance: 0.01,
            record,
            seed: 1,
        };
        let _ = viewer.serve(device, model, &rig, &opts, |_| {});
    });
    Ok(Live { port, token })
}

/// Sends raw bytes and reads the answer's status line (None: no answer in time).
fn exchange(port: u16, request: &[u8]) -> Result<Option<String>, String> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    s.set_write_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    // The server may close early on a bad request; what it answered still counts.
    let _ = s.write_all(request);
    let _ = s.shutdown(std::net::Shutdown::Write);
    let mut out = Vec::new();
    match s.take(1 << 20).read_to_end(&mut out) {
        Ok(_) => {}
        Err(e)
            if matches!(
                e.kind(),
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
            ) =>
        {
            return Ok(None);
        }
        Err(_) => {}
    }
    // The status line, and the body when it is text (an error's JSON message).
    let text = String::from_utf8_lossy(&out);
    let status = text.lines().next().unwrap_or("").trim();
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("");
    let body = if body.is_ascii() {
        &body[..body.len().min(200)]
    } else {
        ""
    };
    Ok(Some(format!("{status} {body}")))
}

fn substitute(raw: &[u8], live: &Live) -> Vec<u8> {
    let text = String::from_utf8_lossy(raw)
        .replace("{{TOKEN}}", &live.token)
        .replace("{{HOST}}", &format!("127.0.0.1:{}", live.port));
    let mut bytes = text.into_bytes();
    // A body's Content-Length as the mutated body has it, unless the mutation broke the
    // header (then the server must cope with the lie).
    if let Some(at) = find(&bytes, b"\r\n\r\n") {
        let body_len = bytes.len() - at - 4;
        let head = String::from_utf8_lossy(&bytes[..at]).into_owned();
        if head.contains("Content-Length: {{LEN}}") {
            let head = head.replace("{{LEN}}", &body_len.to_string());
            let mut out = head.into_bytes();
            out.extend_from_slice(&bytes[at..]);
            bytes = out;
        }
    }
    bytes
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Runs the request in `dir/request.http`; `Err` carries a refusal's status line.
pub fn run(dir: &Path) -> Result<(), String> {
    let live = LIVE.get_or_init(start).as_ref().map_err(|e| e.clone())?;
    let raw = std::fs::read(dir.join("request.http")).map_err(|e| e.to_string())?;
    let request = substitute(&raw, live);
    let answer = exchange(live.port, &request)?;
    let info = format!(
        "GET /info?token={} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n\r\n",
        live.token, live.port
    );
    match exchange(live.port, info.as_bytes()) {
        Ok(Some(l)) if l.starts_with("HTTP/1.1 200") => {}
        other => panic!("the viewer no longer answers /info after this request: {other:?}"),
    }
    match answer {
        None => panic!("the viewer did not answer this request within 10 s"),
        Some(l) if l.starts_with("HTTP/1.1 200") => Ok(()),
        Some(l) => Err(format!("request.http: {l}")),
    }
}

fn request(method: &str, target: &str, body: &str) -> (String, Vec<u8>) {
    let mut r =
        format!("{method} {target} HTTP/1.1\r\nHost: {{{{HOST}}}}\r\nConnection: close\r\n");
    if !body.is_empty() {
        r += "Content-Type: application/json\r\nContent-Length: {{LEN}}\r\n";
    }
    r += "\r\n";
    r += body;
    ("request.http".to_string(), r.into_bytes())
}

pub fn seeds() -> Vec<Case> {
    let c2w = "1,0,0,0.5,0,1,0,0.5,0,0,1,2.5";
    let key = serde_json::to_string(&serde_json::json!({"format": "stegongp-key", "version": 2, "scheme": "prf", "dense": "permute", "m": 9, "secrets": ["07".repeat(32)]})).expect("JSON");
    vec![
        vec![request("GET", "/info?token={{TOKEN}}", "")],
        vec![request(
            "GET",
            &format!("/frame?token={{{{TOKEN}}}}&c2w={c2w}&fov=40&w=32&h=24"),
            "",
        )],
        vec![request(
            "GET",
            &format!("/frame?token={{{{TOKEN}}}}&c2w={c2w}&fov=40&w=16&h=12&fast=1"),
            "",
        )],
        vec![request(
            "POST",
            "/record?token={{TOKEN}}",
            &format!("{{\"c2w\": [{c2w}], \"fov\": 40}}"),
        )],
        vec![request(
            "POST",
            "/key?token={{TOKEN}}",
            &serde_json::to_string(&serde_json::json!({"key_file": key})).expect("JSON"),
        )],
        vec![request("POST", "/forget?token={{TOKEN}}", "{}")],
        vec![request("GET", "/?token={{TOKEN}}", "")],
    ]
}
