//! The Display actor: frames, metrics, camera path.
