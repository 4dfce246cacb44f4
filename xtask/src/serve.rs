//! A small static file server for `dist/` on 127.0.0.1 (std only): correct MIME types
//! (`application/wasm` for streaming compilation), no caching, GET/HEAD only.

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
    let path = target.split(['?', '#']).next().unwrap_or("/");
    let rel = if path.ends_with('/') { format!("{path}index.html") } else { path.to_string() };
    let safe: PathBuf = rel.split('/').filter(|c| !c.is_empty() && *c != "." && *c != "..").collect();
    let file = dir.join(safe);
    let (status, body, ctype) = match (method, std::fs::read(&file)) {
        ("GET" | "HEAD", Ok(bytes)) => ("200 OK", bytes, mime(&file)),
        ("GET" | "HEAD", Err(_)) => ("404 Not Found", b"not found".to_vec(), "text/plain"),
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
