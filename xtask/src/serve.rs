//! A small static file server for `dist/` on 127.0.0.1 (std only): correct MIME types
//! (`application/wasm` for streaming compilation), no caching, GET/HEAD only. Paths are
//! percent-decoded, `.`/`..` segments dropped, and a file whose real location (symlinks
//! resolved) is outside the served directory is not served.

use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

pub struct Server {
    pub addr: SocketAddr,
    handle: std::thread::JoinHandle<()>,
}

impl Server {
    /// Bind 127.0.0.1:`port` (0 = any free port) and serve `dir` on a background thread.
    pub fn start(dir: &Path, port: u16) -> Result<Self> {
        let listener =
            TcpListener::bind(("127.0.0.1", port)).with_context(|| format!("cannot listen on 127.0.0.1:{port}"))?;
        let addr = listener.local_addr()?;
        let dir = dir.to_path_buf();
        let handle = std::thread::spawn(move || {
            for stream in listener.incoming().flatten() {
                let dir = dir.clone();
                std::thread::spawn(move || {
                    let _ = handle(stream, &dir);
                });
            }
        });
        Ok(Self { addr, handle })
    }

    pub fn join(self) {
        let _ = self.handle.join();
    }
}

fn mime(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "html" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript; charset=utf-8",
        "wasm" => "application/wasm",
        "css" => "text/css",
        "png" => "image/png",
        "json" => "application/json",
        "glb" => "model/gltf-binary",
        "svg" => "image/svg+xml",
        _ => "application/octet-stream",
    }
}

/// `%XX` escapes decoded; `None` for a malformed escape or a NUL byte.
fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    let s = String::from_utf8(out).ok()?;
    (!s.contains('\0')).then_some(s)
}

/// The file a request target names inside `dir`, if it is one: the path decoded, split on
/// `/` and `\\`, `.`/`..` and empty segments dropped, `index.html` for a directory, and its real
/// location (symlinks resolved) inside `dir`'s.
fn resolve(dir: &Path, target: &str) -> Option<PathBuf> {
    let path = target.split(['?', '#']).next().unwrap_or("/");
    let path = percent_decode(path)?;
    let rel = if path.ends_with('/') { format!("{path}index.html") } else { path };
    let safe: PathBuf = rel.split(['/', '\\']).filter(|c| !c.is_empty() && *c != "." && *c != "..").collect();
    let file = dir.join(safe).canonicalize().ok()?;
    let root = dir.canonicalize().ok()?;
    (file.starts_with(&root) && file.is_file()).then_some(file)
}

fn handle(mut stream: TcpStream, dir: &Path) -> Result<()> {
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut request = String::new();
    reader.read_line(&mut request)?;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 || line == "\r\n" || line == "\n" {
            break;
        }
    }
    let mut parts = request.split_whitespace();
    let method = parts.next().unwrap_or("");
    let target = parts.next().unwrap_or("/");
    let (status, body, ctype) =
        match (method, resolve(dir, target).and_then(|f| std::fs::read(&f).ok().map(|b| (f, b)))) {
            ("GET" | "HEAD", Some((file, bytes))) => ("200 OK", bytes, mime(&file)),
            ("GET" | "HEAD", None) => ("404 Not Found", b"not found".to_vec(), "text/plain"),
            _ => ("405 Method Not Allowed", b"method not allowed".to_vec(), "text/plain"),
        };
    let header = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(header.as_bytes())?;
    if method != "HEAD" {
        stream.write_all(&body)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    fn get(addr: SocketAddr, request: &str) -> (String, String) {
        let mut s = TcpStream::connect(addr).expect("connect");
        s.write_all(request.as_bytes()).expect("send");
        let mut out = String::new();
        s.read_to_string(&mut out).expect("read");
        let (head, body) = out.split_once("\r\n\r\n").unwrap_or((&out, ""));
        (head.to_string(), body.to_string())
    }

    #[test]
    fn serves_dist_only_with_the_right_types() {
        let base = std::env::temp_dir().join(format!("getavatar-serve-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let dist = base.join("dist");
        std::fs::create_dir_all(dist.join("sub")).expect("mkdir");
        std::fs::write(base.join("secret.txt"), "secret").expect("write");
        std::fs::write(dist.join("index.html"), "<html>").expect("write");
        std::fs::write(dist.join("app.wasm"), "wasm").expect("write");
        std::fs::write(dist.join("sub/x.js"), "js").expect("write");
        #[cfg(unix)]
        std::os::unix::fs::symlink(base.join("secret.txt"), dist.join("link.txt")).expect("symlink");
        let server = Server::start(&dist, 0).expect("start");
        let addr = server.addr;
        assert!(addr.ip().is_loopback(), "binds 127.0.0.1, not every interface: {addr}");
        let req = |path: &str| get(addr, &format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n"));
        let (h, b) = req("/");
        assert!(h.starts_with("HTTP/1.1 200") && h.contains("text/html") && b == "<html>", "{h}");
        let (h, _) = req("/app.wasm");
        assert!(h.contains("Content-Type: application/wasm"), "{h}");
        let (h, b) = req("/sub/x.js?v=1");
        assert!(h.contains("text/javascript") && b == "js", "{h}");
        let (h, _) = req("/sub%2Fx.js");
        assert!(h.starts_with("HTTP/1.1 200"), "encoded slash inside dist is fine: {h}");
        for evil in [
            "/../secret.txt",
            "/%2e%2e/secret.txt",
            "/sub/..%2f..%2fsecret.txt",
            "/..\\secret.txt",
            "/link.txt",
            "/%00",
            "/%zz",
            "//etc/passwd",
        ] {
            let (h, b) = req(evil);
            assert!(h.starts_with("HTTP/1.1 404") && !b.contains("secret"), "{evil}: {h}");
        }
        let (h, _) = get(addr, "POST / HTTP/1.1\r\n\r\n");
        assert!(h.starts_with("HTTP/1.1 405"), "{h}");
        let _ = std::fs::remove_dir_all(&base);
    }
}
