//! The dashboard: one HTML page, its stylesheet and its script, compiled into the binary (no
//! build step). They are public; everything they show comes from the API with the token.

use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;

use super::App;

const INDEX_HTML: &str = include_str!("../../dashboard/index.html");
const DASHBOARD_CSS: &str = include_str!("../../dashboard/dashboard.css");
const DASHBOARD_JS: &str = include_str!("../../dashboard/dashboard.js");

/// The page loads nothing from elsewhere; previews are `blob:` URLs of fetched PNGs (which a
/// script may read back).
const CSP: &str = "default-src 'self'; img-src 'self' blob:; style-src 'self'; \
                   script-src 'self'; connect-src 'self' blob:; frame-ancestors 'none'";

fn file(content_type: &'static str, body: &'static str) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CONTENT_SECURITY_POLICY, CSP),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
}

pub fn routes() -> Router<std::sync::Arc<App>> {
    Router::new()
        .route(
            "/",
            get(|| async { file("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/dashboard.css",
            get(|| async { file("text/css; charset=utf-8", DASHBOARD_CSS) }),
        )
        .route(
            "/dashboard.js",
            get(|| async { file("text/javascript; charset=utf-8", DASHBOARD_JS) }),
        )
}
