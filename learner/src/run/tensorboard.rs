//! TensorBoard scalars: `events.out.tfevents.*` files that `tensorboard
//! --logdir runs/` reads, written beside metrics.csv.
//!
//! Why TensorBoard: it is what RL practitioners already watch (cleanRL,
//! Stable-Baselines3 and rl_games all log there), it overlays runs (LCRL
//! against the global baseline) live, and it needs nothing from us but the
//! file format. metrics.csv stays the source for `lcrl compare` and plots.
//!
//! The format: a sequence of TFRecords, each `u64 length | masked crc32c of
//! the length | Event protobuf | masked crc32c of the data` (little endian),
//! the first Event carrying the file version. Only the messages needed for
//! scalars are declared here (field numbers of tensorflow's event.proto and
//! summary.proto).

use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use prost::Message;

/// tensorflow.Event (the fields scalars use).
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    #[prost(int64, tag = "2")]
    pub step: i64,
    /// oneof `what`: file_version (3) or summary (5).
    #[prost(string, optional, tag = "3")]
    pub file_version: Option<String>,
    #[prost(message, optional, tag = "5")]
    pub summary: Option<Summary>,
}

/// tensorflow.Summary.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// tensorflow.Summary.Value with a simple_value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    #[prost(string, tag = "1")]
    pub tag: String,
    #[prost(float, optional, tag = "2")]
    pub simple_value: Option<f32>,
}

/// TFRecord's checksum: crc32c, rotated and offset so that checksums of
/// data containing checksums stay well distributed.
fn masked_crc(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// Appends scalar events to a new event file in a directory.
pub struct EventWriter {
    file: BufWriter<File>,
    path: PathBuf,
}

impl EventWriter {
    /// Starts `DIR/events.out.tfevents.<unix seconds>.<host>.<pid>`. A new
    /// file per process: TensorBoard reads every file in the directory.
    pub fn create(dir: &Path) -> std::io::Result<EventWriter> {
        std::fs::create_dir_all(dir)?;
        let host = std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_string()).unwrap_or_else(|_| "lcrl".into());
        let path = dir.join(format!("events.out.tfevents.{}.{host}.{}", now().floor() as u64, std::process::id()));
        let mut writer = EventWriter { file: BufWriter::new(File::create(&path)?), path };
        writer.write_event(&Event { wall_time: now(), step: 0, file_version: Some("brain.Event:2".into()), summary: None })?;
        writer.file.flush()?;
        Ok(writer)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Records `values` (tag, value) at `step`; written through on flush.
    pub fn scalars(&mut self, step: i64, values: &[(&str, f64)]) -> std::io::Result<()> {
        let value = values.iter().map(|(tag, v)| SummaryValue { tag: tag.to_string(), simple_value: Some(*v as f32) }).collect();
        self.write_event(&Event { wall_time: now(), step, file_version: None, summary: Some(Summary { value }) })
    }

    pub fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }

    fn write_event(&mut self, event: &Event) -> std::io::Result<()> {
        let data = event.encode_to_vec();
        let length = (data.len() as u64).to_le_bytes();
        self.file.write_all(&length)?;
        self.file.write_all(&masked_crc(&length).to_le_bytes())?;
        self.file.write_all(&data)?;
        self.file.write_all(&masked_crc(&data).to_le_bytes())
    }
}

fn now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// Reads an event file back, checking every checksum (for tests and tools).
pub fn read_events(path: &Path) -> std::io::Result<Vec<Event>> {
    let mut bytes = Vec::new();
    File::open(path)?.read_to_end(&mut bytes)?;
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{}: {what}", path.display()));
    let mut events = Vec::new();
    let mut at = 0;
    while at < bytes.len() {
        let header = bytes.get(at..at + 12).ok_or_else(|| bad("truncated record header"))?;
        let length = u64::from_le_bytes(header[..8].try_into().map_err(|_| bad("header"))?) as usize;
        if masked_crc(&header[..8]).to_le_bytes() != header[8..12] {
            return Err(bad("length checksum mismatch"));
        }
        let data = bytes.get(at + 12..at + 12 + length).ok_or_else(|| bad("truncated record"))?;
        let crc = bytes.get(at + 12 + length..at + 16 + length).ok_or_else(|| bad("truncated checksum"))?;
        if masked_crc(data).to_le_bytes() != crc {
            return Err(bad("data checksum mismatch"));
        }
        events.push(Event::decode(data).map_err(|e| bad(&e.to_string()))?);
        at += 16 + length;
    }
    Ok(events)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masked_crc_matches_tensorflow() {
        // crc32c("123456789") = 0xE3069283 (the standard check value); the
        // mask is tensorflow's ((crc >> 15) | (crc << 17)) + 0xa282ead8.
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        let crc = 0xE306_9283u32;
        assert_eq!(masked_crc(b"123456789"), ((crc >> 15) | (crc << 17)).wrapping_add(0xa282_ead8));
    }

    #[test]
    fn scalars_round_trip_through_an_event_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut writer = EventWriter::create(dir.path()).unwrap();
        writer.scalars(1, &[("episode/return", -12.5), ("episode/length", 50.0)]).unwrap();
        writer.scalars(2, &[("episode/return", -3.25)]).unwrap();
        writer.flush().unwrap();
        let events = read_events(writer.path()).unwrap();
        assert_eq!(events.len(), 3);
        assert_eq!(events[0].file_version.as_deref(), Some("brain.Event:2"));
        let values = &events[1].summary.as_ref().unwrap().value;
        assert_eq!((events[1].step, values[0].tag.as_str(), values[0].simple_value), (1, "episode/return", Some(-12.5)));
        assert_eq!(values[1].simple_value, Some(50.0));
        assert_eq!(events[2].summary.as_ref().unwrap().value[0].simple_value, Some(-3.25));

        // A flipped byte is caught by the checksum.
        let mut bytes = std::fs::read(writer.path()).unwrap();
        let last = bytes.len() - 6;
        bytes[last] ^= 1;
        std::fs::write(writer.path(), bytes).unwrap();
        assert!(read_events(writer.path()).is_err());
    }
}
