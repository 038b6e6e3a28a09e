//! The importers' error type: every message names the file and, where one
//! applies, the place in it (a byte offset for binary data, a line for text).

use std::path::{Path, PathBuf};

/// Why a model could not be imported.
///
/// Display forms: `PATH: byte OFFSET: message` (binary data),
/// `PATH: line N: message` (text), `PATH: message` (no position applies).
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// A problem at a byte offset of binary data.
    #[error("{}: byte {offset}: {message}", path.display())]
    AtByte {
        path: PathBuf,
        offset: u64,
        message: String,
    },
    /// A problem on a line of text (a PLY header, ASCII PLY data, OBJ).
    #[error("{}: line {line}: {message}", path.display())]
    AtLine {
        path: PathBuf,
        line: u64,
        message: String,
    },
    /// A problem with the file as a whole.
    #[error("{}: {message}", path.display())]
    File { path: PathBuf, message: String },
    /// Reading the file failed.
    #[error("{}: read error: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The triangle sink returned an error; import stopped.
    #[error("{}: the triangle sink failed: {source}", path.display())]
    Sink {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl ImportError {
    pub(crate) fn at_byte(path: &Path, offset: u64, message: impl Into<String>) -> Self {
        ImportError::AtByte {
            path: path.to_path_buf(),
            offset,
            message: message.into(),
        }
    }

    pub(crate) fn at_line(path: &Path, line: u64, message: impl Into<String>) -> Self {
        ImportError::AtLine {
            path: path.to_path_buf(),
            line,
            message: message.into(),
        }
    }

    pub(crate) fn file(path: &Path, message: impl Into<String>) -> Self {
        ImportError::File {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        ImportError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn sink(path: &Path, source: std::io::Error) -> Self {
        ImportError::Sink {
            path: path.to_path_buf(),
            source,
        }
    }
}
