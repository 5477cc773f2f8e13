//! `worker --health-listen ADDR`: plain-HTTP probes for an orchestrator (Kubernetes'
//! liveness and readiness probes, see deploy/kubernetes/worker.yaml).
//!
//! - `GET /livez`: 200 while the worker's async runtime answers. A worker whose coordinator
//!   is away is alive (it retries with back-off); only a wedged process fails this.
//! - `GET /readyz`: 200 when the coordinator's `/healthz` answers within two seconds, 503
//!   otherwise.
//!
//! A worker serves no other HTTP, so this is a few lines over a TCP listener rather than a
//! server framework: one request per connection, then close.

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use protocol::client::Client;

/// How long the readiness probe waits for the coordinator.
const COORDINATOR_TIMEOUT: Duration = Duration::from_secs(2);
/// How long a probe connection may take to send its request.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// The longest request head read; probes send a few hundred bytes.
const MAX_HEAD: usize = 8192;

/// Answers probes on `listener` until the task is dropped.
pub async fn serve(listener: TcpListener, client: Client) {
    loop {
        match listener.accept().await {
            Ok((stream, _)) => {
                let client = client.clone();
                tokio::spawn(async move {
                    // A probe that hangs up early is its own problem.
                    let _ = answer(stream, &client).await;
                });
            }
            Err(e) => {
                tracing::warn!("health: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn answer(mut stream: TcpStream, client: &Client) -> std::io::Result<()> {
    let head = match tokio::time::timeout(REQUEST_TIMEOUT, read_head(&mut stream)).await {
        Ok(head) => head?,
        Err(_) => return Ok(()),
    };
    let (status, body) = route(&head, client).await;
    let response = format!(
        "HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

/// The request line and headers, up to the blank line (or [`MAX_HEAD`] bytes).
async fn read_head(stream: &mut TcpStream) -> std::io::Result<String> {
    let mut head = Vec::new();
    let mut buf = [0u8; 1024];
    while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < MAX_HEAD {
        let n = stream.read(&mut buf).await?;
        if n == 0 {
            break;
        }
        head.extend_from_slice(&buf[..n]);
    }
    Ok(String::from_utf8_lossy(&head).into_owned())
}

async fn route(head: &str, client: &Client) -> (&'static str, String) {
    let mut words = head.lines().next().unwrap_or_default().split_whitespace();
    let (method, path) = (words.next().unwrap_or(""), words.next().unwrap_or(""));
    if method != "GET" {
        return ("405 Method Not Allowed", "only GET\n".into());
    }
    match path {
        "/livez" => ("200 OK", "ok\n".into()),
        "/readyz" => match tokio::time::timeout(COORDINATOR_TIMEOUT, client.healthz()).await {
            Ok(Ok(())) => ("200 OK", "ok\n".into()),
            Ok(Err(e)) => (
                "503 Service Unavailable",
                format!("coordinator {}: {e}\n", client.base_url()),
            ),
            Err(_) => (
                "503 Service Unavailable",
                format!(
                    "coordinator {}: no answer within {}s\n",
                    client.base_url(),
                    COORDINATOR_TIMEOUT.as_secs()
                ),
            ),
        },
        _ => ("404 Not Found", "GET /livez or /readyz\n".into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sends `request` to `addr` and returns the whole response.
    async fn ask(addr: std::net::SocketAddr, request: &str) -> String {
        let mut stream = TcpStream::connect(addr).await.unwrap();
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut out = String::new();
        stream.read_to_string(&mut out).await.unwrap();
        out
    }

    async fn probes_for(coordinator: &str) -> std::net::SocketAddr {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let client = Client::new(coordinator, None).unwrap();
        tokio::spawn(serve(listener, client));
        addr
    }

    /// A stand-in coordinator whose every answer is `200 ok`.
    async fn healthy_coordinator() -> String {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        tokio::spawn(async move {
            while let Ok((mut stream, _)) = listener.accept().await {
                let _ = read_head(&mut stream).await;
                let _ = stream
                    .write_all(
                        b"HTTP/1.1 200 OK\r\nContent-Length: 3\r\nConnection: close\r\n\r\nok\n",
                    )
                    .await;
            }
        });
        url
    }

    /// A loopback URL on which nothing listens.
    fn closed_port() -> String {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}", listener.local_addr().unwrap())
    }

    #[tokio::test]
    async fn ready_only_while_the_coordinator_answers_and_alive_regardless() {
        let up = probes_for(&healthy_coordinator().await).await;
        let ready = ask(up, "GET /readyz HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(ready.starts_with("HTTP/1.1 200 OK\r\n"), "{ready}");
        assert!(ready.ends_with("\r\n\r\nok\n"), "{ready}");

        let down = probes_for(&closed_port()).await;
        let ready = ask(down, "GET /readyz HTTP/1.1\r\n\r\n").await;
        assert!(ready.starts_with("HTTP/1.1 503 "), "{ready}");
        assert!(ready.contains("coordinator http://127.0.0.1:"), "{ready}");
        let live = ask(down, "GET /livez HTTP/1.1\r\n\r\n").await;
        assert!(live.starts_with("HTTP/1.1 200 OK\r\n"), "{live}");
    }

    #[tokio::test]
    async fn other_paths_and_methods_are_refused() {
        let addr = probes_for(&closed_port()).await;
        let missing = ask(addr, "GET /metrics HTTP/1.1\r\n\r\n").await;
        assert!(missing.starts_with("HTTP/1.1 404 "), "{missing}");
        let post = ask(addr, "POST /livez HTTP/1.1\r\nContent-Length: 0\r\n\r\n").await;
        assert!(post.starts_with("HTTP/1.1 405 "), "{post}");
        // Garbage, then a hang-up: answered with a 405, and the server stays up.
        let junk = ask(addr, "\x01\x02\r\n\r\n").await;
        assert!(junk.starts_with("HTTP/1.1 405 "), "{junk}");
        let live = ask(addr, "GET /livez HTTP/1.1\r\n\r\n").await;
        assert!(live.contains("200 OK"), "{live}");
    }
}
