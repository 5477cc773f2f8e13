//! The few W3C WebDriver commands the dashboard test sends to chromedriver, over the `reqwest`
//! the farm tests use anyway. A WebDriver crate (fantoccini) pulled in ~40 crates and turned
//! on features of shared dependencies (syn, url's ICU stack) that made `cargo test` recompile
//! much of what the README's render command had just built.

use std::time::{Duration, Instant};

use base64::Engine;
use serde_json::{json, Value};

/// The key under which WebDriver returns an element reference.
const ELEMENT_KEY: &str = "element-6066-11e4-a52e-4f735466cecf";

/// A WebDriver error: the command, and the driver's `error` and `message` (or the transport's).
#[derive(Debug)]
pub struct Error(String);

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// A browser session on a WebDriver server.
pub struct Browser {
    http: reqwest::Client,
    session: String,
}

/// An element of the page, by the session's reference.
pub struct Element<'a> {
    browser: &'a Browser,
    id: String,
}

impl Browser {
    /// Starts a session with `capabilities` (matched as `alwaysMatch`).
    pub async fn connect(driver_url: &str, capabilities: Value) -> Result<Browser, Error> {
        let http = reqwest::Client::new();
        let url = format!("{}/session", driver_url.trim_end_matches('/'));
        let body = json!({ "capabilities": { "alwaysMatch": capabilities } });
        let value = send(http.post(&url).json(&body), "new session").await?;
        let session = value["sessionId"]
            .as_str()
            .ok_or_else(|| Error(format!("new session: no sessionId in {value}")))?;
        Ok(Browser {
            http,
            session: format!("{url}/{session}"),
        })
    }

    async fn post(&self, path: &str, body: Value) -> Result<Value, Error> {
        let url = format!("{}/{path}", self.session);
        send(self.http.post(&url).json(&body), path).await
    }

    async fn get(&self, path: &str) -> Result<Value, Error> {
        let url = format!("{}/{path}", self.session);
        send(self.http.get(&url), path).await
    }

    pub async fn goto(&self, url: &str) -> Result<(), Error> {
        self.post("url", json!({ "url": url })).await.map(drop)
    }

    pub async fn refresh(&self) -> Result<(), Error> {
        self.post("refresh", json!({})).await.map(drop)
    }

    pub async fn current_url(&self) -> Result<String, Error> {
        let value = self.get("url").await?;
        value
            .as_str()
            .map(str::to_owned)
            .ok_or_else(|| Error(format!("url: not a string: {value}")))
    }

    /// Runs `script` as a function body; its return value.
    pub async fn execute(&self, script: &str) -> Result<Value, Error> {
        self.post("execute/sync", json!({ "script": script, "args": [] }))
            .await
    }

    /// Runs `script` as a function body whose last argument is the callback to call with the
    /// result.
    pub async fn execute_async(&self, script: &str) -> Result<Value, Error> {
        self.post("execute/async", json!({ "script": script, "args": [] }))
            .await
    }

    /// The page as a PNG.
    pub async fn screenshot(&self) -> Result<Vec<u8>, Error> {
        let value = self.get("screenshot").await?;
        let text = value
            .as_str()
            .ok_or_else(|| Error(format!("screenshot: not a string: {value}")))?;
        base64::engine::general_purpose::STANDARD
            .decode(text)
            .map_err(|e| Error(format!("screenshot: {e}")))
    }

    /// The first element that matches `css`, waiting up to `timeout` for one to appear.
    pub async fn wait_for(&self, css: &str, timeout: Duration) -> Result<Element<'_>, Error> {
        let start = Instant::now();
        loop {
            let found = self
                .post("element", json!({ "using": "css selector", "value": css }))
                .await;
            match found {
                Ok(value) => {
                    let id = value[ELEMENT_KEY]
                        .as_str()
                        .ok_or_else(|| Error(format!("element: no reference in {value}")))?;
                    return Ok(Element {
                        browser: self,
                        id: id.to_owned(),
                    });
                }
                Err(e) if start.elapsed() >= timeout => return Err(e),
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    }

    /// Ends the session (the browser exits).
    pub async fn close(self) -> Result<(), Error> {
        send(self.http.delete(&self.session), "delete session")
            .await
            .map(drop)
    }
}

impl Element<'_> {
    pub async fn click(&self) -> Result<(), Error> {
        let path = format!("element/{}/click", self.id);
        self.browser.post(&path, json!({})).await.map(drop)
    }

    pub async fn clear(&self) -> Result<(), Error> {
        let path = format!("element/{}/clear", self.id);
        self.browser.post(&path, json!({})).await.map(drop)
    }

    pub async fn send_keys(&self, text: &str) -> Result<(), Error> {
        let path = format!("element/{}/value", self.id);
        self.browser
            .post(&path, json!({ "text": text }))
            .await
            .map(drop)
    }
}

/// Sends a command; the response's `value`, or the WebDriver error it reports.
async fn send(request: reqwest::RequestBuilder, what: &str) -> Result<Value, Error> {
    let response = request
        .send()
        .await
        .map_err(|e| Error(format!("{what}: {e}")))?;
    let status = response.status();
    let body: Value = response
        .json()
        .await
        .map_err(|e| Error(format!("{what}: HTTP {status}, unreadable body: {e}")))?;
    let value = body.get("value").cloned().unwrap_or(Value::Null);
    if status.is_success() {
        Ok(value)
    } else {
        Err(Error(format!(
            "{what}: HTTP {status}: {}: {}",
            value["error"].as_str().unwrap_or("?"),
            value["message"].as_str().unwrap_or("?")
        )))
    }
}
