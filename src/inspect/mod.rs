//! The loop inspector: what a person needs to judge loops by eye. Frame thumbnails
//! (opt-in per session), a session's similarity matrix, and the page itself: static HTML and
//! JavaScript compiled into the binary, served without data (it asks for the key and fetches
//! the session through the same routes as any client).
pub mod similarity;
pub mod thumbnail;

/// The inspector page (one file: markup, style and script; no build step).
pub const PAGE: &str = include_str!("page.html");
/// The page's script.
pub const SCRIPT: &str = include_str!("app.js");
/// The page's style.
pub const STYLE: &str = include_str!("app.css");
