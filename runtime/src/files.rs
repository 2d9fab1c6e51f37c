//! The one atomic file writer every lcrl process uses for what it hands to
//! users and to other processes (run records, graphs, reports).

use std::io::Write as _;
use std::path::Path;

/// Writes `bytes` to `path` whole or not at all: into `.NAME.PID.partial`
/// beside it (the folder is created if needed), flushed to disk (fsync),
/// then renamed over it. A crash leaves the old file or the new one, never
/// half of one. Errors name the file they concern.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = folder_of(path);
    std::fs::create_dir_all(dir).map_err(named("creating", dir))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let partial = dir.join(format!(".{name}.{}.partial", std::process::id()));
    let mut file = std::fs::File::create(&partial).map_err(named("creating", &partial))?;
    file.write_all(bytes).and_then(|()| file.sync_all()).map_err(named("writing", &partial))?;
    drop(file);
    std::fs::rename(&partial, path).map_err(named("renaming over", path))?;
    // The rename itself lives in the folder's entries: without this a
    // power cut can bring back the old file (or none) after we returned.
    sync_dir(dir)
}

/// The folder `path` is in (`.` for a bare name), whose entries a rename
/// of `path` changes.
pub fn folder_of(path: &Path) -> &Path {
    path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."))
}

/// Flushes a folder's entries (names created, renamed or removed in it) to
/// disk, as `fsync` on a file flushes its contents.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir).and_then(|d| d.sync_all()).map_err(named("syncing", dir))
}

/// Flushes the file `path` to disk.
pub fn sync_file(path: &Path) -> std::io::Result<()> {
    std::fs::File::open(path).and_then(|f| f.sync_all()).map_err(named("syncing", path))
}

/// The error, saying what was being done to which file.
fn named<'a>(what: &'a str, path: &'a Path) -> impl FnOnce(std::io::Error) -> std::io::Error + 'a {
    move |e| std::io::Error::new(e.kind(), format!("{what} {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_replaced_whole_and_no_partial_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/summary.json");
        write_atomically(&path, b"old").unwrap();
        write_atomically(&path, b"new contents").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new contents");
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("summary.json")]);
    }

    #[test]
    fn an_unwritable_place_is_named_in_the_error() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("file");
        std::fs::write(&blocker, "x").unwrap();
        let err = write_atomically(&blocker.join("out.json"), b"x").unwrap_err().to_string();
        assert!(err.contains("creating") && err.contains("file"), "{err}");
    }
}
