//! A buffered file reader that knows absolute byte offsets, can seek back,
//! and lets the parsers look into its buffer directly (the fast paths).

use super::ImportError;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// Buffer size; also the longest header, token or line a parser may need
/// to see at once.
pub(crate) const BUF_SIZE: usize = 1 << 20;

pub(crate) struct Input {
    pub path: PathBuf,
    file: File,
    /// `buf[pos..end]` holds the file bytes from offset `base + pos`.
    pub buf: Vec<u8>,
    pub pos: usize,
    pub end: usize,
    pub base: u64,
    len: u64,
}

impl Input {
    pub fn open(path: &Path) -> Result<Input, ImportError> {
        let file =
            File::open(path).map_err(|e| ImportError::file(path, format!("cannot open: {e}")))?;
        let len = file.metadata().map_err(|e| ImportError::io(path, e))?.len();
        Ok(Input {
            path: path.to_path_buf(),
            file,
            buf: vec![0; BUF_SIZE],
            pos: 0,
            end: 0,
            base: 0,
            len,
        })
    }

    /// File length when opened.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Absolute offset of `buf[pos]`.
    #[inline]
    pub fn offset(&self) -> u64 {
        self.base + self.pos as u64
    }

    /// Bytes of the file after the current offset.
    #[inline]
    pub fn remaining(&self) -> u64 {
        self.len.saturating_sub(self.offset())
    }

    #[inline]
    pub fn available(&self) -> usize {
        self.end - self.pos
    }

    pub fn io_err(&self, e: std::io::Error) -> ImportError {
        ImportError::io(&self.path, e)
    }

    /// Makes at least `n` (<= BUF_SIZE) bytes available in `buf[pos..end]`;
    /// false when the file ends first (whatever there is stays available).
    #[inline]
    pub fn fill(&mut self, n: usize) -> Result<bool, ImportError> {
        if self.end - self.pos >= n {
            return Ok(true);
        }
        self.refill(n)
    }

    #[cold]
    fn refill(&mut self, n: usize) -> Result<bool, ImportError> {
        debug_assert!(n <= BUF_SIZE);
        if self.pos > 0 {
            self.buf.copy_within(self.pos..self.end, 0);
            self.base += self.pos as u64;
            self.end -= self.pos;
            self.pos = 0;
        }
        while self.end < n {
            let got = loop {
                match self.file.read(&mut self.buf[self.end..]) {
                    Ok(k) => break k,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => return Err(self.io_err(e)),
                }
            };
            if got == 0 {
                return Ok(false);
            }
            self.end += got;
        }
        Ok(true)
    }

    /// Up to `n` bytes from the current offset (fewer at the end of the file).
    pub fn peek(&mut self, n: usize) -> Result<&[u8], ImportError> {
        self.fill(n)?;
        let k = n.min(self.available());
        Ok(&self.buf[self.pos..self.pos + k])
    }

    /// Moves to absolute offset `off`.
    pub fn seek(&mut self, off: u64) -> Result<(), ImportError> {
        if off >= self.base && off <= self.base + self.end as u64 {
            self.pos = (off - self.base) as usize;
            return Ok(());
        }
        self.file
            .seek(SeekFrom::Start(off))
            .map_err(|e| self.io_err(e))?;
        self.base = off;
        self.pos = 0;
        self.end = 0;
        Ok(())
    }

    /// Skips `n` bytes; false (without moving) when fewer remain in the file.
    pub fn skip(&mut self, n: u64) -> Result<bool, ImportError> {
        if n > self.remaining() {
            return Ok(false);
        }
        if n <= self.available() as u64 {
            self.pos += n as usize;
            Ok(true)
        } else {
            let off = self.offset() + n;
            self.seek(off)?;
            Ok(true)
        }
    }

    /// The next line (without `\n` and a trailing `\r`) as a range of `buf`,
    /// or None at the end of the file; lines longer than BUF_SIZE - 1 bytes
    /// are an error (`Err(None)` lets the caller word it).
    pub fn line(&mut self) -> Result<Option<(usize, usize)>, Option<ImportError>> {
        let mut scanned = 0;
        loop {
            let hay = &self.buf[self.pos + scanned..self.end];
            if let Some(i) = hay.iter().position(|&c| c == b'\n') {
                let start = self.pos;
                let mut stop = self.pos + scanned + i;
                self.pos = stop + 1;
                if stop > start && self.buf[stop - 1] == b'\r' {
                    stop -= 1;
                }
                return Ok(Some((start, stop)));
            }
            scanned = self.available();
            if scanned >= BUF_SIZE - 1 {
                return Err(None);
            }
            if !self.fill(scanned + 1).map_err(Some)? {
                if self.available() == 0 {
                    return Ok(None);
                }
                let start = self.pos;
                let mut stop = self.end;
                self.pos = self.end;
                if stop > start && self.buf[stop - 1] == b'\r' {
                    stop -= 1;
                }
                return Ok(Some((start, stop)));
            }
        }
    }
}
