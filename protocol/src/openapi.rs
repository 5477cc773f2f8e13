//! The API as an OpenAPI 3.1 document (`GET /api/v1/openapi.json`), generated rather than
//! written: the paths, statuses, bodies, query parameters and security come from
//! [`crate::routes::ROUTES`], the schemas from the wire types' `ToSchema` derives. A route added
//! to the table is in the document; a body naming a type that is not a component leaves a
//! dangling `$ref`, which the coordinator's spec test refuses.

use utoipa::openapi::content::ContentBuilder;
use utoipa::openapi::path::{HttpMethod, OperationBuilder, ParameterBuilder, ParameterIn};
use utoipa::openapi::request_body::RequestBodyBuilder;
use utoipa::openapi::response::ResponseBuilder;
use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, Schema, Type};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityRequirement, SecurityScheme};
use utoipa::openapi::{InfoBuilder, OpenApi, Paths, Ref, RefOr, Required};
use utoipa::OpenApi as _;

use crate::routes::{Access, Body, QueryValue, Route, ROUTES};
use crate::{PART_JOB, PART_SCENE};

/// The security scheme of the bearer token (`--token`).
pub const TOKEN_SCHEME: &str = "token";
/// The security scheme of the scrape-only metrics token (`--metrics-token`).
pub const METRICS_TOKEN_SCHEME: &str = "metricsToken";

/// Every wire type; the types they hold are collected with them.
#[derive(utoipa::OpenApi)]
#[openapi(components(schemas(
    crate::JobSpec,
    crate::AdaptiveSpec,
    crate::PassInfo,
    crate::Convergence,
    crate::PassLease,
    crate::JobInfo,
    crate::JobState,
    crate::TileFailure,
    crate::TileState,
    crate::TilePage,
    crate::TileInfo,
    crate::JobCamera,
    crate::WorkerState,
    crate::WorkerLease,
    crate::WorkerInfo,
    crate::WorkerRegistration,
    crate::WorkerIdentity,
    crate::LeaseRequest,
    crate::Lease,
    crate::LeaseStatus,
    crate::Completion,
    crate::FailureReport,
    crate::Bundle,
    crate::BundleFile,
    crate::ApiError,
)))]
struct WireTypes;

/// The whole document.
pub fn document() -> OpenApi {
    let mut doc = WireTypes::openapi();
    doc.info = InfoBuilder::new()
        .title("Tessera coordinator")
        .version(env!("CARGO_PKG_VERSION"))
        .description(Some(
            "A ray-tracing render farm's coordinator: jobs, tiles, leases and workers. \
             Generated from the protocol crate's route table and wire types; docs/api.md has \
             the prose. Every 4xx/5xx body is an ApiError; any route may also answer 405 (wrong \
             method) and 413 (body over the upload limit).",
        ))
        .build();
    let components = doc.components.get_or_insert_with(Default::default);
    let bearer = |what: &str| {
        SecurityScheme::Http(
            HttpBuilder::new()
                .scheme(HttpAuthScheme::Bearer)
                .description(Some(what))
                .build(),
        )
    };
    components.add_security_scheme(
        TOKEN_SCHEME,
        bearer("The coordinator's --token (TESSERA_TOKEN), when it has one."),
    );
    components.add_security_scheme(
        METRICS_TOKEN_SCHEME,
        bearer("The scrape-only --metrics-token (TESSERA_METRICS_TOKEN): /metrics only."),
    );
    let mut paths = Paths::new();
    for route in ROUTES {
        paths.add_path_operation(route.full_path(), vec![method(route)], operation(route));
    }
    doc.paths = paths;
    doc
}

/// The document as JSON.
pub fn json() -> String {
    document()
        .to_pretty_json()
        .expect("a document of plain values serialises")
}

fn method(route: &Route) -> HttpMethod {
    match route.method {
        "GET" => HttpMethod::Get,
        "POST" => HttpMethod::Post,
        "PUT" => HttpMethod::Put,
        "DELETE" => HttpMethod::Delete,
        "PATCH" => HttpMethod::Patch,
        other => unreachable!("the route table uses no {other}"),
    }
}

fn operation(route: &Route) -> utoipa::openapi::path::Operation {
    let mut op = OperationBuilder::new()
        .operation_id(Some(format!("{:?}", route.id)))
        .summary(Some(route.summary));
    for name in route.path_params() {
        let (schema, what) = if name == "hash" {
            (string(), "lower-case hex SHA-256")
        } else {
            (integer(), "a numeric id (anything else is a 404)")
        };
        op = op.parameter(
            ParameterBuilder::new()
                .name(name)
                .parameter_in(ParameterIn::Path)
                .required(Required::True)
                .description(Some(what))
                .schema(Some(schema)),
        );
    }
    for q in route.query {
        let schema = match q.value {
            QueryValue::Integer => integer(),
            QueryValue::OneOf(words) => RefOr::T(Schema::Object(
                ObjectBuilder::new()
                    .schema_type(Type::String)
                    .enum_values(Some(words.iter().copied()))
                    .build(),
            )),
        };
        op = op.parameter(
            ParameterBuilder::new()
                .name(q.name)
                .parameter_in(ParameterIn::Query)
                .required(Required::False)
                .description(Some(q.meaning))
                .schema(Some(schema)),
        );
    }
    if route.request != Body::Empty {
        let (media, schema) = content(route.request);
        op = op.request_body(Some(
            RequestBodyBuilder::new()
                .content(media, ContentBuilder::new().schema(schema).build())
                .required(Some(if route.request_required {
                    Required::True
                } else {
                    Required::False
                }))
                .build(),
        ));
    }
    for answer in route.statuses() {
        let mut response = ResponseBuilder::new().description(answer.meaning);
        if answer.body != Body::Empty {
            let (media, schema) = content(answer.body);
            response = response.content(media, ContentBuilder::new().schema(schema).build());
        }
        op = op.response(answer.status.to_string(), response.build());
    }
    let security = match route.access {
        // An empty list overrides nothing; an empty requirement says "no credentials".
        Access::Open => vec![SecurityRequirement::default()],
        Access::Token => vec![SecurityRequirement::new(TOKEN_SCHEME, Vec::<String>::new())],
        Access::MetricsToken => vec![
            SecurityRequirement::new(TOKEN_SCHEME, Vec::<String>::new()),
            SecurityRequirement::new(METRICS_TOKEN_SCHEME, Vec::<String>::new()),
        ],
    };
    op.securities(Some(security)).build()
}

fn integer() -> RefOr<Schema> {
    RefOr::T(Schema::Object(
        ObjectBuilder::new()
            .schema_type(Type::Integer)
            .minimum(Some(0))
            .build(),
    ))
}

fn string() -> RefOr<Schema> {
    RefOr::T(Schema::Object(
        ObjectBuilder::new().schema_type(Type::String).build(),
    ))
}

fn component(name: &str) -> RefOr<Schema> {
    RefOr::Ref(Ref::from_schema_name(name))
}

/// The media type and schema of a body.
fn content(body: Body) -> (&'static str, Option<RefOr<Schema>>) {
    match body {
        Body::Empty => ("application/octet-stream", None),
        Body::Json(name) => ("application/json", Some(component(name))),
        Body::JsonList(name) => (
            "application/json",
            Some(RefOr::T(Schema::Array(
                ArrayBuilder::new().items(component(name)).build(),
            ))),
        ),
        Body::Strings => (
            "application/json",
            Some(RefOr::T(Schema::Array(
                ArrayBuilder::new().items(string()).build(),
            ))),
        ),
        Body::Bytes(media) => (media, Some(string())),
        Body::Submission => (
            "multipart/form-data",
            Some(RefOr::T(Schema::Object(
                ObjectBuilder::new()
                    .property(PART_JOB, component("JobSpec"))
                    .property(PART_SCENE, string())
                    .required(PART_SCENE)
                    .description(Some(
                        "The job's settings, the scene file, and one part per asset named by \
                         the path the scene writes.",
                    ))
                    .additional_properties(Some(string()))
                    .build(),
            ))),
        ),
    }
}
