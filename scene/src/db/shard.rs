//! Shards of a database: `dray shard DB --of N --out DIR` writes
//! `DIR/shard-I` for I in 0..N, each a database holding only the voxels
//! whose id is I modulo N, for a store on a host of its own. A shard keeps
//! the whole manifest (clients ask any store for it), its blobs back to
//! back in id order in `voxels.dray`, and `shard.dray`, one line of text
//! naming which shard it is (`dray shard 1/4`).

use super::manifest::{Manifest, MANIFEST_FILE, VOXELS_FILE};
use super::{Database, DbError};
use crate::progress::Progress;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The file that makes a database directory a shard.
pub const SHARD_FILE: &str = "shard.dray";

/// Most shards one database is cut into.
pub const MAX_SHARDS: u32 = 1024;

/// Which voxels a shard holds: ids equal to `index` modulo `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardOf {
    /// The residue.
    pub index: u32,
    /// The modulus.
    pub count: u32,
}

impl ShardOf {
    /// Whether the shard holds voxel `id`.
    pub fn holds(&self, id: u32) -> bool {
        id % self.count == self.index
    }

    /// Whether every voxel of `(index, count)` is in this shard.
    pub fn covers(&self, index: u32, count: u32) -> bool {
        count.is_multiple_of(self.count) && index % self.count == self.index
    }

    /// The shard file's text.
    fn to_text(self) -> String {
        format!("dray shard {}/{}\n", self.index, self.count)
    }

    /// Parses the shard file's text.
    fn parse(text: &str) -> Result<ShardOf, String> {
        let bad = || format!("{:?} is not `dray shard I/N` with I < N", text.trim());
        let rest = text.trim().strip_prefix("dray shard ").ok_or_else(bad)?;
        let (i, n) = rest.split_once('/').ok_or_else(bad)?;
        let (index, count): (u32, u32) =
            (i.parse().map_err(|_| bad())?, n.parse().map_err(|_| bad())?);
        if count == 0 || index >= count || count > MAX_SHARDS {
            return Err(bad());
        }
        Ok(ShardOf { index, count })
    }
}

impl std::fmt::Display for ShardOf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Reads `dir`'s shard file, if it has one.
pub(crate) fn read_shard_file(dir: &Path) -> Result<Option<ShardOf>, DbError> {
    let path = dir.join(SHARD_FILE);
    match std::fs::read_to_string(&path) {
        Ok(text) => ShardOf::parse(&text)
            .map(Some)
            .map_err(|message| DbError::Layout { path, message }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(DbError::Io { path, source }),
    }
}

/// Where each held voxel's blob starts in a shard's `voxels.dray`,
/// indexed by `id / count`, and the file's length.
pub(crate) fn local_offsets(m: &Manifest, shard: ShardOf) -> (Vec<u64>, u64) {
    let mut at = 0u64;
    let offsets = m
        .voxels
        .iter()
        .enumerate()
        .filter(|(id, _)| shard.holds(*id as u32))
        .map(|(_, v)| {
            let here = at;
            at = at.saturating_add(v.compressed_bytes);
            here
        })
        .collect();
    (offsets, at)
}

/// Why a database could not be sharded.
#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    /// Reading the database failed (a voxel's blob is corrupt, say).
    #[error(transparent)]
    Db(#[from] DbError),
    /// Writing a shard failed.
    #[error("{path}: {source}")]
    Io {
        /// What was being written.
        path: PathBuf,
        /// What happened.
        source: std::io::Error,
    },
    /// The request makes no sense (a count of 0, a shard as input, a shard
    /// directory already there).
    #[error("{0}")]
    Invalid(String),
}

/// Writes `out/shard-I` for I in 0..`count`; an existing shard directory is
/// never overwritten. Each shard is written beside its place and renamed
/// into it once complete, so a failure leaves no half shard.
pub fn write_shards(
    db: &Database,
    count: u32,
    out: &Path,
    progress: &Progress,
) -> Result<Vec<PathBuf>, ShardError> {
    if count == 0 || count > MAX_SHARDS {
        return Err(ShardError::Invalid(format!(
            "--of {count}: a database is cut into 1 to {MAX_SHARDS} shards"
        )));
    }
    if let Some(s) = db.shard() {
        return Err(ShardError::Invalid(format!(
            "{} is already shard {s} of a database: shard the whole database",
            db.dir().display()
        )));
    }
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ShardError::Io { path, source }
    };
    let dirs: Vec<PathBuf> = (0..count).map(|i| out.join(format!("shard-{i}"))).collect();
    if let Some(d) = dirs.iter().find(|d| d.exists()) {
        return Err(ShardError::Invalid(format!(
            "{} exists: remove it, or write the shards elsewhere (--out)",
            d.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(io(out))?;
    let manifest_bytes =
        std::fs::read(db.dir().join(MANIFEST_FILE)).map_err(io(&db.dir().join(MANIFEST_FILE)))?;
    let voxels = db.manifest.voxels.len() as u32;
    progress.stage("writing shards", u64::from(voxels));
    for (index, dir) in dirs.iter().enumerate() {
        let shard = ShardOf {
            index: index as u32,
            count,
        };
        let tmp = out.join(format!(".shard-{index}.partial"));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
        }
        std::fs::create_dir(&tmp).map_err(io(&tmp))?;
        std::fs::write(tmp.join(MANIFEST_FILE), &manifest_bytes).map_err(io(&tmp))?;
        let blobs_path = tmp.join(VOXELS_FILE);
        let file = std::fs::File::create(&blobs_path).map_err(io(&blobs_path))?;
        let mut w = std::io::BufWriter::new(file);
        for id in (shard.index..voxels).step_by(count as usize) {
            w.write_all(&db.read_blob(id)?).map_err(io(&blobs_path))?;
            progress.advance(1);
        }
        w.into_inner()
            .map_err(|e| e.into_error())
            .and_then(|f| f.sync_all())
            .map_err(io(&blobs_path))?;
        std::fs::write(tmp.join(SHARD_FILE), shard.to_text()).map_err(io(&tmp))?;
        std::fs::rename(&tmp, dir).map_err(io(dir))?;
    }
    progress.finish();
    Ok(dirs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shard_file_reads_back_and_refuses_nonsense() {
        let s = ShardOf { index: 3, count: 8 };
        assert_eq!(ShardOf::parse(&s.to_text()), Ok(s));
        for bad in [
            "",
            "dray shard 8/8",
            "dray shard 1/0",
            "shard 1/2",
            "dray shard 1/2/3",
            "dray shard 1/2000",
        ] {
            assert!(ShardOf::parse(bad).is_err(), "{bad}");
        }
    }

    proptest::proptest! {
        /// Any shard file's bytes read back as a shard or are refused.
        #[test]
        fn any_shard_file_reads_or_is_refused(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..40)) {
            let text = String::from_utf8_lossy(&bytes);
            if let Ok(s) = ShardOf::parse(&text) {
                proptest::prop_assert!(s.index < s.count && s.count <= MAX_SHARDS);
            }
        }

        #[test]
        fn shard_files_round_trip(count in 1u32..=MAX_SHARDS, index in 0u32..MAX_SHARDS) {
            let s = ShardOf { index: index % count, count };
            proptest::prop_assert_eq!(ShardOf::parse(&s.to_text()), Ok(s));
        }
    }

    #[test]
    fn a_shard_covers_the_finer_shards_inside_it() {
        let s = ShardOf { index: 1, count: 2 };
        assert!(s.covers(1, 2) && s.covers(3, 4) && s.covers(1, 4));
        assert!(!s.covers(0, 2) && !s.covers(2, 4) && !s.covers(0, 1) && !s.covers(1, 3));
    }
}
