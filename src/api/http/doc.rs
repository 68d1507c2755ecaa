//! The OpenAPI document's frame: its title and description, the bearer scheme, the error answers
//! every route shares, and the shapes of what is sent as a form or a raw body (they are read by
//! hand, so no Rust type says them). Each route's part is on its handler (`#[utoipa::path]`), and
//! the router is built from those (`super::routes`), so a served route is always documented.
use crate::api::error::ErrorBody;
use utoipa::openapi::header::HeaderBuilder;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{ContentBuilder, Ref, RefOr, Response, ResponseBuilder};
use utoipa::{IntoParams, Modify, OpenApi, ToResponse, ToSchema};

#[derive(OpenApi)]
#[openapi(
    info(title = "loopd", description = include_str!("api.md")),
    servers((url = "http://127.0.0.1:8080")),
    security(("bearer" = [])),
    modifiers(&Bearer),
    components(
        schemas(ErrorBody),
        responses(BadRequest, NotFound, Conflict, TooLarge, Overloaded, Unavailable, Unauthorized, Forbidden)
    )
)]
pub struct ApiDoc;

struct Bearer;

impl Modify for Bearer {
    fn modify(&self, api: &mut utoipa::openapi::OpenApi) {
        let scheme = HttpBuilder::new()
            .scheme(HttpAuthScheme::Bearer)
            .description(Some("A tenant's key, or the admin key (docs/security.md)."))
            .build();
        api.components.get_or_insert_with(Default::default).add_security_scheme("bearer", SecurityScheme::Http(scheme));
    }
}

/// An error answer: its description, and `header` when it sets one.
fn error(description: &str, header: Option<(&str, utoipa::openapi::schema::Type)>) -> RefOr<Response> {
    let body = ContentBuilder::new().schema(Some(Ref::from_schema_name("Error"))).build();
    let mut r = ResponseBuilder::new().description(description).content("application/json", body);
    if let Some((name, ty)) = header {
        r = r.header(name, HeaderBuilder::new().schema(utoipa::openapi::schema::Object::with_type(ty)).build());
    }
    r.build().into()
}

/// The error answers routes share, each a named response of the document.
macro_rules! error_response {
    ($($name:ident: $description:expr, $header:expr;)*) => {$(
        pub struct $name;
        impl<'s> ToResponse<'s> for $name {
            fn response() -> (&'s str, RefOr<Response>) {
                (stringify!($name), error($description, $header))
            }
        }
    )*};
}

use utoipa::openapi::schema::Type;
error_response! {
    BadRequest: "Invalid input.", None;
    NotFound: "Unknown session, frame or job.", None;
    Conflict: "Session or frame id already taken, or an image for a session of another descriptor space \
               (the message names both ids).", None;
    TooLarge: "Body, image bytes or decoded image size above the configured limit (OUT_OF_RANGE over gRPC).", None;
    Overloaded: "Inference queue full, a tenant's limit reached, or too many jobs; retry after the Retry-After \
                 seconds.", Some(("Retry-After", Type::Integer));
    Unavailable: "Shutting down, or storage failed (a full disk): writes are refused, and readiness is 503, until \
                  the store takes writes again (no restart needed); in a cluster (serve --cluster), its database \
                  has no writable primary or cannot be reached. Retry after the Retry-After seconds.",
                  Some(("Retry-After", Type::Integer));
    Unauthorized: "No key, or a malformed, unknown or revoked one (keys on).", Some(("WWW-Authenticate", Type::String));
    Forbidden: "A tenant's key on an admin route, or tenant routes on a server without an admin key.", None;
}

/// Raw bytes (an image, a tar archive, a bag).
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
pub struct Binary(pub Vec<u8>);

/// A frame or query as a multipart form: an `image` file part and text fields (the JSON-valued
/// ones as JSON text).
#[derive(ToSchema)]
#[allow(dead_code)] // a document shape: the form is read field by field (super::form)
pub struct FrameForm {
    image: Option<Binary>,
    /// The image's registered depth image: 16-bit PNG/PGM/TIFF in the session camera's
    /// depth_scale units per metre (default 1000), or float TIFF in metres. Loops verified with
    /// it get metric poses.
    depth: Option<Binary>,
    /// The right image of a stereo pair (a session camera with stereo); not with depth.
    right: Option<Binary>,
    robot_id: Option<String>,
    /// A number.
    timestamp: Option<String>,
    /// An integer; unset: assigned.
    frame_id: Option<String>,
    /// A Pose as JSON text.
    pose: Option<String>,
    /// A JSON object as text.
    metadata: Option<String>,
    /// QueryOptions as JSON text.
    options: Option<String>,
    /// A write's idempotency key.
    idempotency_key: Option<String>,
}

/// A frame's fields in the query string when its body is the raw image.
#[derive(IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)] // a document shape: the query string is read with the form (super::form)
pub struct RawFrameFields {
    /// Raw-body form only.
    robot_id: Option<String>,
    /// Raw-body form only.
    timestamp: Option<f64>,
    /// Raw-body form only; unset: assigned (a query: the stored frame to query with).
    frame_id: Option<u64>,
    /// Raw-body form only: a write's idempotency key.
    idempotency_key: Option<String>,
}

/// A sequence job's options, as form fields or in the query string: any field of the query
/// options, the robot, the order of image files and what to read of a bag.
#[derive(IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)] // a document shape: read by `SequenceRequest::from_form`
pub struct SequenceFields {
    /// The frames' robot (default `sequence`; a bag's: the topic's namespace).
    robot_id: Option<String>,
    min_score: Option<f32>,
    /// A loop's least confidence (default: the server's loop_confidence).
    #[param(minimum = 0, maximum = 1)]
    min_confidence: Option<f32>,
    /// Default 3.
    exclude_last_frames: Option<u64>,
    /// Default 1.
    #[param(minimum = 1, maximum = 1000)]
    k: Option<u64>,
    /// Default true.
    verify: Option<bool>,
    #[param(minimum = 1, maximum = 50)]
    verify_candidates: Option<u64>,
    #[param(minimum = 8, maximum = 10000)]
    min_inliers: Option<u64>,
    /// Default true.
    sequence: Option<bool>,
    #[param(minimum = 1, maximum = 200)]
    sequence_length: Option<u64>,
    min_sequence_margin: Option<f32>,
    /// Image files in the order sent (`sent`, the default) or by natural name order (`name`).
    #[param(pattern = "^(sent|name)$")]
    order: Option<String>,
    /// Bags: image topics, comma-separated (default: the bag's only image topic).
    topic: Option<String>,
    /// Bags: keep every Nth message of each topic (default 1).
    #[param(minimum = 1)]
    every: Option<u64>,
    /// Bags: smallest step between kept frames of a topic, in seconds of header stamp (default 0).
    #[param(minimum = 0)]
    min_dt: Option<f64>,
    /// Bags: the camera's pose topic (nav_msgs/Odometry, geometry_msgs/PoseStamped or
    /// PoseWithCovarianceStamped), interpolated to each image's stamp (not across 1 s gaps).
    pose_topic: Option<String>,
    /// Bags: the camera's registered depth images (sensor_msgs/Image 16UC1 mm or 32FC1 m),
    /// the nearest within 50 ms of each image: verified loops get metric poses.
    depth_topic: Option<String>,
    /// Bags: the right images of a stereo pair (sensor_msgs/Image or CompressedImage), the nearest
    /// within 50 ms of each image, for a session camera with stereo: verified loops get metric poses.
    right_topic: Option<String>,
    /// Bags, instead of pose_topic: the frame the camera's pose is taken in from /tf and
    /// /tf_static (with camera_frame).
    odom_frame: Option<String>,
    /// Bags: the camera's tf frame (with odom_frame).
    camera_frame: Option<String>,
}

/// A sequence as a multipart form: image files, one tar archive, or the files of a bag, with
/// the job's fields (SequenceFields) as text parts.
#[derive(ToSchema)]
#[allow(dead_code)] // a document shape: read by `SequenceRequest::from_form`
pub struct SequenceForm {
    image: Option<Vec<Binary>>,
    /// A tar archive of images (natural name order).
    archive: Option<Binary>,
    /// A bag; several parts: the files of a split rosbag2 bag, in order.
    bag: Option<Vec<Binary>>,
    robot_id: Option<String>,
    order: Option<String>,
    topic: Option<String>,
}

/// The document as `openapi.yaml` holds it.
pub fn yaml() -> Result<String, String> {
    super::openapi().to_yaml().map_err(|e| e.to_string())
}
