//! API keys: `lpd_<key id>_<secret>`, 256 random bits of secret, shown once; only the secret's
//! SHA-256 is kept, compared in constant time.
use rand::RngCore;
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

pub const PREFIX: &str = "lpd_";

/// Fewest characters of an admin key: the server and `loopd tenant` refuse a shorter one.
pub const MIN_ADMIN_KEY: usize = 16;

/// The admin key: the file's first line, else `LOOPD_ADMIN_KEY` (never a flag value, which any
/// user could read in `ps`); None when neither gives one, an error when it is shorter than
/// [`MIN_ADMIN_KEY`] or the file cannot be read.
pub fn read_admin_key(file: Option<&std::path::Path>) -> anyhow::Result<Option<String>> {
    let (key, source) = match file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| anyhow::anyhow!("reading the admin key file {}: {e}", path.display()))?;
            (text.lines().next().unwrap_or("").trim().to_string(), format!("the admin key in {}", path.display()))
        }
        None => match std::env::var("LOOPD_ADMIN_KEY") {
            Ok(key) if !key.trim().is_empty() => (key.trim().to_string(), "LOOPD_ADMIN_KEY".to_string()),
            _ => return Ok(None),
        },
    };
    anyhow::ensure!(key.len() >= MIN_ADMIN_KEY, "{source} is shorter than {MIN_ADMIN_KEY} characters");
    Ok(Some(key))
}

/// A new key: (key id, the whole key to give the client once, the secret's hash to keep).
pub fn new_key() -> (String, String, [u8; 32]) {
    let mut id = [0u8; 6];
    let mut secret = [0u8; 32];
    rand::rng().fill_bytes(&mut id);
    rand::rng().fill_bytes(&mut secret);
    let (id, secret) = (hex(&id), hex(&secret));
    let hash = digest(&secret);
    (id.clone(), format!("{PREFIX}{id}_{secret}"), hash)
}

/// A presented key as (key id, secret), if it has the shape of one.
pub fn parse(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix(PREFIX)?;
    let (id, secret) = rest.split_once('_')?;
    let hexish = |s: &str, n: usize| s.len() == n && s.bytes().all(|b| b.is_ascii_hexdigit());
    (hexish(id, 12) && hexish(secret, 64)).then_some((id, secret))
}

pub fn digest(secret: &str) -> [u8; 32] {
    Sha256::digest(secret.as_bytes()).into()
}

/// Whether `secret` hashes to `hash`, in time that does not depend on where they differ.
pub fn matches(secret: &str, hash: &[u8; 32]) -> bool {
    digest(secret).ct_eq(hash).into()
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

pub fn unhex(s: &str) -> Option<[u8; 32]> {
    let mut out = [0u8; 32];
    if s.len() != 64 {
        return None;
    }
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_key_parses_and_matches_only_its_hash() {
        let (id, key, hash) = new_key();
        let (pid, secret) = parse(&key).expect("a new key parses");
        assert_eq!(pid, id);
        assert!(matches(secret, &hash));
        let (_, other, _) = new_key();
        assert!(!matches(parse(&other).unwrap().1, &hash));
        assert_eq!(unhex(&hex(&hash)), Some(hash));
        for bad in ["", "lpd_", "lpd_zz_yy", &key[..key.len() - 1], &key.replace("lpd_", "xyz_")] {
            assert!(parse(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn an_admin_key_file_gives_its_first_line_and_a_short_key_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (good, short) = (dir.path().join("good"), dir.path().join("short"));
        std::fs::write(&good, "  admin-key-0123456789  \nsecond line\n").unwrap();
        std::fs::write(&short, "admin-key-01234\n").unwrap();
        assert_eq!(read_admin_key(Some(&good)).unwrap().as_deref(), Some("admin-key-0123456789"));
        let e = read_admin_key(Some(&short)).unwrap_err().to_string();
        assert!(e.contains("shorter than 16 characters"), "{e}");
        assert!(read_admin_key(Some(&dir.path().join("missing"))).is_err());
    }
}
