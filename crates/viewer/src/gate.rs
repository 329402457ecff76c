//! The viewer's front door: it takes each TCP connection, reads the request's head and body
//! itself within fixed bounds, and only then hands the request to the HTTP server behind
//! it, on a Unix socket in a folder only this user can enter.
//!
//! Why: tiny_http 0.12 drains an unread body on drop into a buffer of the length the
//! request declares (tiny-http/tiny-http#290), before any handler can refuse it, so one
//! request saying `Content-Length: 10000000000000` made the viewer abort, token or not.
//! Here a head over [`MAX_HEAD`] bytes, a body over [`MAX_BODY`], a chunked body or a
//! client slower than [`TIMEOUT`] gets an error status and the connection is closed; what
//! reaches the server is one bounded request with `Connection: close`.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Largest request head (request line and headers).
pub const MAX_HEAD: usize = 16 << 10;
/// Largest request body (a key file is a few hundred bytes).
pub const MAX_BODY: u64 = 64 << 10;
/// A client must send its request within this (and take the answer no slower).
pub const TIMEOUT: Duration = Duration::from_secs(10);
/// The server must send each part of its answer within this (the first counted from when
/// the request reached it).
pub const ANSWER_TIMEOUT: Duration = Duration::from_secs(600);

/// How long the front door waits on each side.
#[derive(Clone, Copy, Debug)]
pub struct Waits {
    /// For the client's request, and for the client to take each part of the answer.
    pub client: Duration,
    /// For the server's answer.
    pub answer: Duration,
}

impl Default for Waits {
    fn default() -> Self {
        Waits {
            client: TIMEOUT,
            answer: ANSWER_TIMEOUT,
        }
    }
}

/// Why a request is turned away before the server sees it.
#[derive(Debug, PartialEq, Eq)]
pub struct Refusal {
    pub status: u16,
    pub reason: &'static str,
}

/// A request read whole: its head (ending in the blank line) and body.
#[derive(Debug, PartialEq, Eq)]
pub struct Checked {
    pub head: Vec<u8>,
    pub body: Vec<u8>,
}

fn refuse(status: u16, reason: &'static str) -> Refusal {
    Refusal { status, reason }
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Reads one request from `r` within the bounds, and rewrites its head so that the
/// connection closes after the answer.
pub fn read_request(r: &mut impl Read) -> Result<Checked, Refusal> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 4096];
    let head_end = loop {
        if let Some(i) = find(&buf, b"\r\n\r\n") {
            break i + 4;
        }
        if buf.len() > MAX_HEAD {
            return Err(refuse(431, "request head too large"));
        }
        let n = r
            .read(&mut chunk)
            .map_err(|_| refuse(408, "request not received in time"))?;
        if n == 0 {
            return Err(refuse(400, "connection closed before the request's end"));
        }
        buf.extend_from_slice(&chunk[..n]);
    };
    if head_end > MAX_HEAD {
        return Err(refuse(431, "request head too large"));
    }
    let head = std::str::from_utf8(&buf[..head_end])
        .map_err(|_| refuse(400, "request head is not text"))?;
    let mut lines = head.split("\r\n");
    let request_line = lines.next().unwrap_or("");
    let mut length: Option<u64> = None;
    let mut kept = vec![request_line.to_string()];
    for line in lines.filter(|l| !l.is_empty()) {
        let (name, value) = line
            .split_once(':')
            .ok_or(refuse(400, "malformed header line"))?;
        let name = name.trim();
        if name.eq_ignore_ascii_case("transfer-encoding") {
            return Err(refuse(501, "chunked or encoded bodies are not accepted"));
        }
        if name.eq_ignore_ascii_case("content-length") {
            let n: u64 = value
                .trim()
                .parse()
                .map_err(|_| refuse(400, "Content-Length is not a number"))?;
            if length.is_some_and(|l| l != n) {
                return Err(refuse(400, "conflicting Content-Length headers"));
            }
            length = Some(n);
        }
        if name.eq_ignore_ascii_case("connection") {
            continue; // replaced by Connection: close below
        }
        kept.push(line.to_string());
    }
    let length = length.unwrap_or(0);
    if length > MAX_BODY {
        return Err(refuse(413, "request body too large"));
    }
    let mut body = buf[head_end..].to_vec();
    body.truncate(length as usize);
    while (body.len() as u64) < length {
        let want = (length as usize - body.len()).min(chunk.len());
        let n = r
            .read(&mut chunk[..want])
            .map_err(|_| refuse(408, "request body not received in time"))?;
        if n == 0 {
            return Err(refuse(400, "connection closed before the body's end"));
        }
        body.extend_from_slice(&chunk[..n]);
    }
    kept.push("Connection: close".into());
    let mut head = kept.join("\r\n").into_bytes();
    head.extend_from_slice(b"\r\n\r\n");
    Ok(Checked { head, body })
}

fn answer_refusal(stream: &mut TcpStream, r: &Refusal) {
    let body = format!("{{\"error\": \"{}\"}}", r.reason);
    let text = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{}",
        r.status,
        r.reason,
        body.len(),
        body
    );
    let _ = stream.write_all(text.as_bytes());
}

fn serve_one(mut client: TcpStream, inner: &Path, waits: Waits) {
    let _ = client.set_read_timeout(Some(waits.client));
    let _ = client.set_write_timeout(Some(waits.client));
    let req = match read_request(&mut client) {
        Ok(r) => r,
        Err(r) => return answer_refusal(&mut client, &r),
    };
    let Ok(mut server) = UnixStream::connect(inner) else {
        return answer_refusal(&mut client, &refuse(503, "viewer unavailable"));
    };
    let _ = server.set_read_timeout(Some(waits.answer));
    let _ = server.set_write_timeout(Some(waits.client));
    if server.write_all(&req.head).is_err() || server.write_all(&req.body).is_err() {
        return answer_refusal(&mut client, &refuse(503, "viewer unavailable"));
    }
    // The server closes after its answer (Connection: close); pass it on as it comes. A
    // server silent for the whole wait gets the client a status rather than a bare close.
    let mut buf = [0u8; 16 << 10];
    let mut passed = 0usize;
    let (status, reason) = loop {
        match server.read(&mut buf) {
            Ok(0) => break (502, "the viewer closed without an answer"),
            Ok(n) => {
                if client.write_all(&buf[..n]).is_err() {
                    return;
                }
                passed += n;
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(_) => break (504, "the viewer did not answer in time"),
        }
    };
    if passed == 0 {
        answer_refusal(&mut client, &refuse(status, reason));
    }
}

/// A private folder for the server's socket, removed when the viewer ends.
pub struct SocketDir(PathBuf);

impl SocketDir {
    pub fn new(random: &str) -> std::io::Result<Self> {
        use std::os::unix::fs::DirBuilderExt;
        let dir = std::env::temp_dir().join(format!("stegongp-viewer-{random}"));
        std::fs::DirBuilder::new().mode(0o700).create(&dir)?;
        Ok(SocketDir(dir))
    }

    pub fn socket(&self) -> PathBuf {
        self.0.join("http.sock")
    }
}

impl Drop for SocketDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Accepts connections on `front` for ever, a thread each, forwarding checked requests to
/// the server on `inner`.
pub fn spawn(front: TcpListener, inner: PathBuf, waits: Waits) {
    std::thread::spawn(move || {
        for conn in front.incoming() {
            let Ok(conn) = conn else { continue };
            let inner = inner.clone();
            std::thread::spawn(move || serve_one(conn, &inner, waits));
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(s: &str) -> Result<Checked, Refusal> {
        read_request(&mut s.as_bytes())
    }

    #[test]
    fn a_plain_request_passes_with_connection_close() {
        let r = read("POST /key?token=t HTTP/1.1\r\nHost: h\r\nConnection: keep-alive\r\nContent-Length: 4\r\n\r\nabcdEXTRA").unwrap();
        let head = String::from_utf8(r.head).unwrap();
        assert!(head.starts_with("POST /key?token=t HTTP/1.1\r\nHost: h\r\n"));
        assert!(head.ends_with("Connection: close\r\n\r\n"));
        assert!(!head.contains("keep-alive"));
        assert_eq!(r.body, b"abcd");
    }

    #[test]
    fn declared_sizes_are_bounded_before_reading() {
        let huge = format!("POST / HTTP/1.1\r\nContent-Length: {}\r\n\r\nx", u64::MAX);
        assert_eq!(read(&huge).unwrap_err().status, 413);
        let over = format!(
            "POST / HTTP/1.1\r\nContent-Length: {}\r\n\r\n",
            MAX_BODY + 1
        );
        assert_eq!(read(&over).unwrap_err().status, 413);
        let nan = "POST / HTTP/1.1\r\nContent-Length: 99999999999999999999999\r\n\r\n";
        assert_eq!(read(nan).unwrap_err().status, 400);
        let two = "POST / HTTP/1.1\r\nContent-Length: 1\r\nContent-Length: 2\r\n\r\nab";
        assert_eq!(read(two).unwrap_err().status, 400);
        let chunked = "POST / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n";
        assert_eq!(read(chunked).unwrap_err().status, 501);
        let long_head = format!("GET / HTTP/1.1\r\nX: {}\r\n\r\n", "a".repeat(MAX_HEAD));
        assert_eq!(read(&long_head).unwrap_err().status, 431);
        let short_body = "POST / HTTP/1.1\r\nContent-Length: 10\r\n\r\nabc";
        assert_eq!(read(short_body).unwrap_err().status, 400);
        assert_eq!(read("GET / HTTP/1.1\r\nHost").unwrap_err().status, 400);
    }

    /// What a client gets through a front door whose server reads the request, waits
    /// `delay`, then writes `answer` (nothing: it closes) and closes.
    fn through_the_gate(delay: Duration, answer: &'static [u8], waits: Waits) -> String {
        use std::os::unix::net::UnixListener;
        let dir = tempfile::tempdir().unwrap();
        let sock = dir.path().join("s.sock");
        let inner = UnixListener::bind(&sock).unwrap();
        let server = std::thread::spawn(move || {
            let (mut conn, _) = inner.accept().unwrap();
            let mut got = Vec::new();
            let mut b = [0u8; 256];
            while find(&got, b"\r\n\r\n").is_none() {
                let n = conn.read(&mut b).unwrap();
                assert!(n > 0, "the request never reached the server");
                got.extend_from_slice(&b[..n]);
            }
            std::thread::sleep(delay);
            let _ = conn.write_all(answer);
        });
        let front = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = front.local_addr().unwrap().port();
        spawn(front, sock, waits);
        let mut client = TcpStream::connect(("127.0.0.1", port)).unwrap();
        client
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        client
            .write_all(b"GET /info HTTP/1.1\r\nHost: h\r\n\r\n")
            .unwrap();
        let mut got = String::new();
        client.read_to_string(&mut got).unwrap();
        server.join().unwrap();
        got
    }

    const OK: &[u8] = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nConnection: close\r\n\r\nok";

    #[test]
    fn a_slow_answer_is_passed_on_whole_past_the_clients_bound() {
        // The server takes four times the client's bound (a key being opened, or requests
        // queued behind one): the answer still arrives, untouched.
        let waits = Waits {
            client: Duration::from_millis(100),
            answer: Duration::from_secs(20),
        };
        let got = through_the_gate(Duration::from_millis(400), OK, waits);
        assert_eq!(got.as_bytes(), OK);
    }

    #[test]
    fn a_silent_or_mute_server_gets_the_client_a_status_not_a_bare_close() {
        let waits = Waits {
            client: Duration::from_secs(5),
            answer: Duration::from_millis(200),
        };
        let late = through_the_gate(Duration::from_millis(1500), OK, waits);
        assert!(late.starts_with("HTTP/1.1 504 "), "{late}");
        assert!(late.contains("did not answer in time"), "{late}");
        let mute = through_the_gate(Duration::ZERO, b"", waits);
        assert!(mute.starts_with("HTTP/1.1 502 "), "{mute}");
    }
}
