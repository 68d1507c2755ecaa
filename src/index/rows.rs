//! A session's rows (its unit descriptors: f16 bits or f32, row after row), in memory or in a
//! file mapped into memory (issue #33: a map's rows should not be the process's memory).
//!
//! A mapped column writes each row to a file of its own (created under the store's `rows/` folder
//! and unlinked at once: nothing else can open it, and nothing is left behind by a crash) and
//! reads the rows through a shared mapping of that file. Its pages are the kernel's page cache:
//! written back to disk and dropped under memory pressure, where rows in memory could not be
//! (these machines have no swap). The process keeps at most `resident` bytes of them mapped in:
//! once reads since the last release exceed that, the column tells the kernel it does not need
//! its pages (`MADV_DONTNEED`; a shared file mapping keeps their contents in the file, the next
//! read maps them in again, from the page cache while they are there). An approximate session's
//! query reads a few hundred rows, so its rows cost the process little; an exact scan reads them
//! all (exact sessions are the small ones: `auto` switches at `--approx-min-frames`).
//!
//! Rows are derived data like the graph: sled / the cluster log hold them, and a session's rows
//! are written again from there when it loads. A write to the file that fails (a full disk)
//! moves the column back into memory: nothing is lost, and the log says so.
use std::fs::File;
use std::marker::PhantomData;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

/// A row value as stored: f16 bits or f32.
pub(crate) trait Value: Copy + Send + Sync + 'static {
    fn put(self, out: &mut Vec<u8>);
}

impl Value for u16 {
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_ne_bytes());
    }
}

impl Value for f32 {
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_ne_bytes());
    }
}

/// Where and how a session's rows are mapped.
#[derive(Clone, Copy, Debug)]
pub struct Mapping<'a> {
    /// The folder the (unlinked) file is created in.
    pub dir: &'a Path,
    /// Bytes of rows the process keeps mapped in before it releases them.
    pub resident: usize,
}

/// The smallest mapping (a mapping grows by doubling; the file grows row by row).
const MIN_MAPPED_BYTES: usize = 1 << 20;

pub(crate) enum Column<T: Value> {
    Memory(Vec<T>),
    Mapped(Mapped<T>),
}

pub(crate) struct Mapped<T: Value> {
    file: File,
    /// Covers at least `len` values (None while empty).
    map: Option<memmap2::Mmap>,
    mapped_bytes: usize,
    /// Values written.
    len: usize,
    /// Bytes read since the pages were last released.
    read: AtomicUsize,
    resident: usize,
    _values: PhantomData<T>,
}

impl<T: Value> Column<T> {
    /// Rows in memory, or in a new unlinked file in `mapping.dir` (in memory when that file
    /// cannot be made, logged).
    pub(crate) fn new(mapping: Option<Mapping<'_>>) -> Self {
        let Some(m) = mapping else { return Column::Memory(Vec::new()) };
        match unlinked_file(m.dir) {
            Ok(file) => Column::Mapped(Mapped {
                file,
                map: None,
                mapped_bytes: 0,
                len: 0,
                read: AtomicUsize::new(0),
                resident: m.resident,
                _values: PhantomData,
            }),
            Err(e) => {
                tracing::warn!(dir = %m.dir.display(), error = %e, "rows file not created; the session's rows stay in memory");
                Column::Memory(Vec::new())
            }
        }
    }

    /// Rows in `file`, a file the store keeps under a name of its own (`store/kept.rs`): the
    /// first `values` values are taken as written, anything after them is cut off, and new rows
    /// are appended. The data directory is this server's alone (sled's lock), and a later load
    /// of the same session puts a new file in its place (a rename) rather than writing this one.
    pub(crate) fn in_file(file: File, values: usize, resident: usize) -> std::io::Result<Self> {
        file.set_len((values * std::mem::size_of::<T>()) as u64)?;
        let mut m = Mapped {
            file,
            map: None,
            mapped_bytes: 0,
            len: 0,
            read: AtomicUsize::new(0),
            resident,
            _values: PhantomData,
        };
        m.cover(values)?;
        m.len = values;
        Ok(Column::Mapped(m))
    }

    /// The file a mapped column writes (None in memory).
    pub(crate) fn file(&self) -> Option<&File> {
        match self {
            Column::Memory(_) => None,
            Column::Mapped(m) => Some(&m.file),
        }
    }

    pub(crate) fn is_mapped(&self) -> bool {
        matches!(self, Column::Mapped(_))
    }

    /// Bytes of the process's own memory the rows take (a mapped column's pages are the page
    /// cache's, counted as [`Column::file_bytes`]).
    pub(crate) fn memory_bytes(&self) -> usize {
        match self {
            Column::Memory(v) => v.capacity() * std::mem::size_of::<T>(),
            Column::Mapped(_) => 0,
        }
    }

    /// Bytes of rows in the file (0 in memory).
    pub(crate) fn file_bytes(&self) -> usize {
        match self {
            Column::Memory(_) => 0,
            Column::Mapped(m) => m.len * std::mem::size_of::<T>(),
        }
    }

    /// Appends values (whole rows).
    pub(crate) fn extend(&mut self, values: impl Iterator<Item = T>) {
        match self {
            Column::Memory(v) => v.extend(values),
            Column::Mapped(m) => {
                let values: Vec<T> = values.collect();
                if let Err(e) = m.append(&values) {
                    tracing::warn!(error = %e, values = m.len, "writing rows to their file failed; the session's rows move into memory");
                    let mut held = m.as_slice().to_vec();
                    held.extend_from_slice(&values);
                    *self = Column::Memory(held);
                }
            }
        }
    }

    /// Counts `values` read (a scan, re-scored candidates); a mapped column releases its pages
    /// from the process once the reads since the last release pass its resident bytes.
    pub(crate) fn note_read(&self, values: usize) {
        if let Column::Mapped(m) = self {
            // A file within the bound may stay mapped in whole (an exact session reads it all
            // at every query; releasing it would only add page faults).
            if m.len * std::mem::size_of::<T>() <= m.resident {
                return;
            }
            let bytes = values * std::mem::size_of::<T>();
            let read = m.read.fetch_add(bytes, Relaxed) + bytes;
            if read >= m.resident {
                m.read.store(0, Relaxed);
                m.release();
            }
        }
    }
}

impl<T: Value> std::ops::Deref for Column<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match self {
            Column::Memory(v) => v,
            Column::Mapped(m) => m.as_slice(),
        }
    }
}

impl<T: Value> Mapped<T> {
    fn as_slice(&self) -> &[T] {
        match &self.map {
            None => &[],
            // SAFETY: the mapping starts on a page boundary (aligned for u16 and f32) and covers
            // `mapped_bytes >= len * size_of::<T>()` bytes; the first `len` values of the file
            // were written (pwrite, visible through the shared mapping: one page cache) before
            // `len` counted them (or, for a kept file, were in it when the column took it and
            // the file was cut to them), so every byte read lies inside the file. Only this
            // column writes the file or changes its length (an unlinked file has no name to open
            // it by; a kept file lies in the data directory, which sled's lock makes this
            // server's alone, and a later load of the session renames a new file over its name
            // instead of writing it), appending past `len` through `&mut self`, so no value in
            // the returned slice changes while the `&self` borrow lasts. u16 and f32 accept any
            // bit pattern.
            Some(map) => unsafe { std::slice::from_raw_parts(map.as_ptr() as *const T, self.len) },
        }
    }

    fn append(&mut self, values: &[T]) -> std::io::Result<()> {
        let size = std::mem::size_of::<T>();
        let mut bytes = Vec::with_capacity(std::mem::size_of_val(values));
        values.iter().for_each(|v| v.put(&mut bytes));
        // A write that fails leaves `len` as it was: the values before it are whole.
        self.file.write_all_at(&bytes, (self.len * size) as u64)?;
        let len = self.len + values.len();
        self.cover(len)?;
        self.len = len;
        Ok(())
    }

    /// Maps (again, larger) so that the mapping covers `len` values.
    fn cover(&mut self, len: usize) -> std::io::Result<()> {
        let size = std::mem::size_of::<T>();
        if len * size > self.mapped_bytes {
            let bytes = (len * size).max(2 * self.mapped_bytes).max(MIN_MAPPED_BYTES);
            // SAFETY: a shared read-only mapping of a file only this column writes (see
            // `as_slice`); the mapping may reach past the file's end, but reads stay below
            // `len` values, which the file holds.
            let map = unsafe { memmap2::MmapOptions::new().len(bytes).map(&self.file)? };
            self.map = Some(map);
            self.mapped_bytes = bytes;
        }
        Ok(())
    }

    /// Unmaps the pages from the process (they stay in the file and, while there is room, in the
    /// page cache).
    fn release(&self) {
        if let Some(map) = &self.map {
            // SAFETY: MADV_DONTNEED on a shared file mapping drops the process's page table
            // entries only; the data is the file's, and the next read maps it in again with the
            // same contents (unlike a private or anonymous mapping, whose pages it would zero).
            // Concurrent readers see the same bytes before and after.
            if let Err(e) = unsafe { map.unchecked_advise(memmap2::UncheckedAdvice::DontNeed) } {
                tracing::debug!(error = %e, "releasing mapped rows failed");
            }
        }
    }
}

/// A new file in `dir`, unlinked at once (kept open: its blocks are freed when it is closed).
fn unlinked_file(dir: &Path) -> std::io::Result<File> {
    std::fs::create_dir_all(dir)?;
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let path = dir.join(format!("rows-{}-{}", std::process::id(), NEXT.fetch_add(1, Relaxed)));
    let file = std::fs::OpenOptions::new().read(true).write(true).create_new(true).open(&path)?;
    std::fs::remove_file(&path)?;
    Ok(file)
}

/// Bytes of this process's mappings of files under `dir` that are mapped in now (the `Rss` of
/// each in /proc/self/smaps; a row file's mapping reads "`<dir>/rows-…` (deleted)"). 0 where
/// /proc cannot be read.
pub fn mapped_bytes(dir: &Path) -> usize {
    let Ok(smaps) = std::fs::read_to_string("/proc/self/smaps") else { return 0 };
    let Some(dir) = dir.to_str() else { return 0 };
    // A mapping's first line starts with its address range ("7f3a…-7f3b…").
    let header = |l: &str| {
        l.split_whitespace()
            .next()
            .is_some_and(|f| f.contains('-') && f.chars().all(|c| c.is_ascii_hexdigit() || c == '-'))
    };
    let (mut kb, mut inside) = (0usize, false);
    for line in smaps.lines() {
        if header(line) {
            inside = line.contains(dir);
        } else if let Some(v) = line.strip_prefix("Rss:").filter(|_| inside) {
            kb += v.trim().trim_end_matches(" kB").parse::<usize>().unwrap_or(0);
        }
    }
    kb * 1024
}
