//! Why an experiment cannot run, or stopped.

use std::path::PathBuf;

/// Every error names what it is about: the experiment file and the key,
/// an output file, or the run.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// A key of the experiment file, or of the config it builds, is wrong.
    #[error("{}: {key}: {problem}", file.display())]
    Invalid {
        /// The experiment file.
        file: PathBuf,
        /// The key, as the file writes it (`repeat`, `[set] clients.count`,
        /// `[sweep] clients.cache_mb = 0`, `plot[1].y`).
        key: String,
        /// What is wrong.
        problem: String,
    },
    /// The experiment file cannot be read, or is not valid TOML (the
    /// parser's message names the line and the key).
    #[error("{}: {message}", file.display())]
    Unreadable {
        /// The experiment file.
        file: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// An output file or directory could not be read or written.
    #[error("{}: {message}", path.display())]
    Output {
        /// The file or directory.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The model could not be generated or preprocessed.
    #[error("model {}: {message}", path.display())]
    Model {
        /// The database being made.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A run failed.
    #[error("run {run}: {message}")]
    Run {
        /// The point and repeat.
        run: String,
        /// What went wrong.
        message: String,
    },
}

impl ExperimentError {
    pub(crate) fn invalid(
        file: &std::path::Path,
        key: impl Into<String>,
        problem: impl std::fmt::Display,
    ) -> ExperimentError {
        ExperimentError::Invalid {
            file: file.to_path_buf(),
            key: key.into(),
            problem: problem.to_string(),
        }
    }

    pub(crate) fn output(path: &std::path::Path, e: impl std::fmt::Display) -> ExperimentError {
        ExperimentError::Output {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    }
}
