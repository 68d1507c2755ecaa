//! Image files as sequences: which names are images, and natural name order.

pub const IMAGE_EXTENSIONS: [&str; 7] = ["jpg", "jpeg", "png", "bmp", "tif", "tiff", "webp"];

pub fn is_image(name: &str) -> bool {
    name.rsplit_once('.').is_some_and(|(_, e)| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// Sort key for natural order: "2.png" before "10.png" (digit runs compare as numbers).
pub fn natural_key(s: &str) -> Vec<(bool, u64, String)> {
    let mut out = Vec::new();
    let mut rest = s;
    while let Some(c) = rest.chars().next() {
        let digit = c.is_ascii_digit();
        let end = rest.find(|ch: char| ch.is_ascii_digit() != digit).unwrap_or(rest.len());
        let (run, tail) = rest.split_at(end);
        out.push((!digit, if digit { run.parse().unwrap_or(u64::MAX) } else { 0 }, run.to_string()));
        rest = tail;
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn natural_order() {
        let mut v = vec!["10.png", "2.png", "1.png", "a10", "a9"];
        v.sort_by_cached_key(|s| super::natural_key(s));
        assert_eq!(v, ["1.png", "2.png", "10.png", "a9", "a10"]);
        assert!(super::is_image("x.JPG") && !super::is_image("notes.txt"));
    }
}
