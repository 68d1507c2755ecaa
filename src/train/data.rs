//! Training data: images grouped into places, from traversals with ground truth (read by
//! `loopd eval`'s readers), a places CSV, or unlabelled folders (positives by augmentation).
use crate::eval::gt::GroundTruth;
use crate::eval::run::{frames_in_range, list_images};
use anyhow::{bail, Context, Result};
use std::collections::{BTreeMap, HashMap};
use std::ops::Range;
use std::path::{Path, PathBuf};

/// One training image.
#[derive(Clone, Debug)]
pub struct Sample {
    pub path: PathBuf,
    pub place: usize,
    /// Samples of one group share a timeline (`position`): a pair closer than the tolerance is
    /// neither positive nor negative.
    pub group: usize,
    pub position: Option<i64>,
}

#[derive(Clone, Debug)]
pub struct Place {
    pub samples: Vec<usize>,
    /// Views come from augmenting one image (unlabelled data).
    pub augmented: bool,
}

#[derive(Default, Debug)]
pub struct TrainSet {
    pub samples: Vec<Sample>,
    pub places: Vec<Place>,
    /// Ground-truth tolerance per group (frames).
    pub tolerance: Vec<i64>,
    /// One line per source, for the heads file's metadata.
    pub sources: Vec<String>,
}

/// Two traversals (or one sequence) with loop ground truth, as `loopd eval` takes them.
#[derive(Clone, Debug)]
pub struct TraversalSource {
    pub sequence: PathBuf,
    pub query_sequence: Option<PathBuf>,
    pub gt: String,
    pub camera: Option<usize>,
    pub tolerance: usize,
    /// Frame indices (in natural name order) used from each folder.
    pub range: Option<Range<usize>>,
    pub filter: Option<String>,
}

/// Disjoint-set forest over frame nodes: frames linked by the ground truth form one place.
struct Places(Vec<usize>);

impl Places {
    fn find(&mut self, mut i: usize) -> usize {
        while self.0[i] != i {
            self.0[i] = self.0[self.0[i]];
            i = self.0[i];
        }
        i
    }
    fn union(&mut self, a: usize, b: usize) {
        let (a, b) = (self.find(a), self.find(b));
        self.0[a.max(b)] = a.min(b);
    }
}

impl TrainSet {
    fn group(&mut self, tolerance: usize) -> usize {
        self.tolerance.push(tolerance as i64);
        self.tolerance.len() - 1
    }

    /// Adds places of two or more images; a place of one image (no positive) is left out.
    fn add_places(&mut self, groups: Vec<Vec<(PathBuf, Option<i64>)>>, group: usize) -> usize {
        let mut added = 0;
        for members in groups.into_iter().filter(|m| m.len() >= 2) {
            let place = self.places.len();
            let mut ids = Vec::with_capacity(members.len());
            for (path, position) in members {
                ids.push(self.samples.len());
                self.samples.push(Sample { path, place, group, position });
            }
            self.places.push(Place { samples: ids, augmented: false });
            added += 1;
        }
        added
    }

    pub fn add_traversal(&mut self, s: &TraversalSource) -> Result<()> {
        let refs = frames_in_range(&s.sequence, s.filter.as_deref(), s.range.as_ref())?;
        let queries = s
            .query_sequence
            .as_deref()
            .map(|q| frames_in_range(q, s.filter.as_deref(), s.range.as_ref()))
            .transpose()?;
        let nq = queries.as_ref().map_or(refs.len(), Vec::len);
        let offset = s.range.as_ref().map_or(0, |r| r.start);
        // Ground-truth indices are of the whole folder; the range keeps a window of them.
        let total = offset + nq.min(refs.len());
        let gt = GroundTruth::load(&s.gt, s.camera, total)?;
        let local = |i: usize, n: usize| i.checked_sub(offset).filter(|&l| l < n);
        let nr = refs.len();
        let mut uf = Places((0..nr + if queries.is_some() { nq } else { 0 }).collect());
        // Each frame's place on the route: its own index (query frames: that of the reference frame
        // they match, set below).
        let mut position: Vec<i64> =
            (0..uf.0.len()).map(|i| (offset + if i < nr { i } else { i - nr }) as i64).collect();
        let mut pairs = 0;
        for (&q, rs) in &gt.loops {
            for &r in rs {
                // Without a range every frame named must exist; a range keeps a window on purpose.
                if s.range.is_none() && (r >= nr || q >= nq) {
                    bail!("ground truth {} names frame pair ({q}, {r}) but there are {nq} query and {nr} reference frames", s.gt);
                }
                let (Some(ql), Some(rl)) = (local(q, nq), local(r, nr)) else { continue };
                match &queries {
                    Some(_) => {
                        uf.union(nr + ql, rl);
                        position[nr + ql] = (offset + rl) as i64;
                    }
                    None => uf.union(ql, rl),
                }
                pairs += 1;
            }
        }
        if pairs == 0 {
            bail!("ground truth {} links no two frames of {} in the range used", s.gt, s.sequence.display());
        }
        let mut by_root: BTreeMap<usize, Vec<(PathBuf, Option<i64>)>> = BTreeMap::new();
        for node in 0..uf.0.len() {
            let path = if node < nr {
                refs[node].clone()
            } else {
                queries.as_ref().map_or(PathBuf::new(), |q| q[node - nr].clone())
            };
            let root = uf.find(node);
            by_root.entry(root).or_default().push((path, Some(position[node])));
        }
        let group = self.group(s.tolerance);
        let places = self.add_places(by_root.into_values().collect(), group);
        self.sources.push(format!(
            "{}{} gt {} tolerance {} range {}: {places} places",
            s.sequence.display(),
            s.query_sequence.as_ref().map_or(String::new(), |q| format!(" + {}", q.display())),
            s.gt,
            s.tolerance,
            s.range.as_ref().map_or("all".into(), |r| format!("{}..{}", r.start, r.end))
        ));
        Ok(())
    }

    /// A CSV of images (first column, relative to the CSV's folder) and place columns whose
    /// values together name the place (e.g. floor and area).
    pub fn add_places_csv(&mut self, path: &Path, place_columns: &[String]) -> Result<()> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().context("empty places CSV")?.split(',').map(str::trim).collect();
        let cols: Vec<usize> = place_columns
            .iter()
            .map(|c| {
                header
                    .iter()
                    .position(|h| h == c)
                    .with_context(|| format!("{}: no column '{c}' (columns: {})", path.display(), header.join(", ")))
            })
            .collect::<Result<_>>()?;
        let base = path.parent().unwrap_or(Path::new("."));
        let mut places: HashMap<String, Vec<(PathBuf, Option<i64>)>> = HashMap::new();
        let mut order = Vec::new();
        for (n, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let fields: Vec<&str> = line.split(',').map(str::trim).collect();
            let image = base.join(fields[0]);
            if !image.is_file() {
                bail!("{}:{}: image {} does not exist", path.display(), n + 2, image.display());
            }
            let key = cols.iter().map(|&c| fields.get(c).copied().unwrap_or("")).collect::<Vec<_>>().join("/");
            if !places.contains_key(&key) {
                order.push(key.clone());
            }
            places.entry(key).or_default().push((image, None));
        }
        let groups: Vec<_> = order.iter().filter_map(|k| places.remove(k)).collect();
        let group = self.group(0);
        let added = self.add_places(groups, group);
        if added == 0 {
            bail!("{}: no place has two images, so there are no positives", path.display());
        }
        self.sources.push(format!("{} places by {}: {added} places", path.display(), place_columns.join("+")));
        Ok(())
    }

    /// Every image of a folder is a place of its own; its views are augmentations of it.
    pub fn add_unlabelled(&mut self, dir: &Path) -> Result<()> {
        let files = list_images(dir, None)?;
        let group = self.group(0);
        for path in &files {
            let place = self.places.len();
            self.samples.push(Sample { path: path.clone(), place, group, position: None });
            self.places.push(Place { samples: vec![self.samples.len() - 1], augmented: true });
        }
        self.sources.push(format!("{} unlabelled: {} images", dir.display(), files.len()));
        Ok(())
    }

    /// Whether samples `a` and `b` may serve as a negative pair: other places, and not within
    /// the tolerance of each other on a shared timeline.
    pub fn negative(&self, a: usize, b: usize) -> bool {
        let (sa, sb) = (&self.samples[a], &self.samples[b]);
        if sa.place == sb.place {
            return false;
        }
        if sa.group != sb.group {
            return true;
        }
        let tol = self.tolerance[sa.group];
        // Against every view of the other's place: a frame near a positive of mine is no negative.
        let near = |x: &Sample, place: usize| {
            self.places[place].samples.iter().any(|&k| match (x.position, self.samples[k].position) {
                (Some(p), Some(q)) => (p - q).abs() <= tol,
                _ => false,
            })
        };
        !near(sa, sb.place) && !near(sb, sa.place)
    }
}
