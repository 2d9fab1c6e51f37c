//! Tests of `checkpoint`.

use super::*;

fn meta(episode: usize) -> CheckpointMeta {
    CheckpointMeta { episode, ..CheckpointMeta::start("lti-paper", Algo::Ppo, Connection::Local, 1, 1, vec![vec![1]], TrainConfig::default()) }
}

/// A whole safetensors file of one f32 tensor.
fn tensors() -> Vec<u8> {
    tensor_of(1.5)
}

/// A whole safetensors file of one f32 tensor holding `value`.
fn tensor_of(value: f32) -> Vec<u8> {
    let header = br#"{"w":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}}"#;
    let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
    bytes.extend_from_slice(header);
    bytes.extend_from_slice(&value.to_le_bytes());
    bytes
}

/// Issue 71: a checkpoint whose weights hold a NaN is not intact, so
/// resume skips it for the newest finite one and pruning does not
/// count it; one written with non-finite weights never lands.
#[test]
fn a_checkpoint_with_a_non_finite_weight_is_never_resumed_from() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("checkpoints");
    let ten = write(&root, 10);
    let twenty = root.join("ep000020");
    write_folder(&twenty, &meta(20), |staging| {
        std::fs::write(staging.join("actor.safetensors"), tensor_of(f32::NAN)).map_err(io(staging))?;
        std::fs::write(staging.join("critic_adam.safetensors"), tensor_of(1.0)).map_err(io(staging))
    })
    .unwrap();
    let err = check_intact(&twenty).unwrap_err().to_string();
    assert!(err.contains("actor.safetensors holds a non-finite weight"), "{err}");
    assert_eq!(latest_checkpoint(dir.path()), Some(ten.clone()));
    // The staged check refuses the same folder before it is sealed.
    let thirty = root.join("ep000030");
    let refused = write_folder(&thirty, &meta(30), |staging| {
        std::fs::write(staging.join("actor.safetensors"), tensor_of(f32::INFINITY)).map_err(io(staging))?;
        check_staged_finite(staging)
    })
    .unwrap_err()
    .to_string();
    assert!(refused.contains("checkpoint not written") && refused.contains("last finite checkpoint"), "{refused}");
    assert!(!thirty.exists());
    assert_eq!(latest_checkpoint(dir.path()), Some(ten));
}

/// What an agent writes, with `tag` to tell two writes apart.
fn fill(tag: &str) -> impl FnOnce(&Path) -> Result<(), LearnerError> + '_ {
    move |staging| {
        std::fs::write(staging.join("actor.safetensors"), tensors()).map_err(io(staging))?;
        std::fs::write(staging.join("agent.json"), format!("{{\"tag\":\"{tag}\"}}")).map_err(io(staging))
    }
}

fn write(root: &Path, episode: usize) -> PathBuf {
    let target = root.join(format!("ep{episode:06}"));
    write_folder(&target, &meta(episode), fill("first")).unwrap();
    target
}

fn names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    names
}

/// A process killed inside `write_folder` leaves its staging folder
/// with an empty checkpoint.json (the e2e study killed with SIGKILL hit
/// it): resuming must take the newest complete checkpoint, or none.
#[test]
fn a_staging_folder_left_by_a_kill_is_never_the_checkpoint() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    let staging = root.join(".ep000025.partial");
    std::fs::create_dir_all(&staging).unwrap();
    std::fs::write(staging.join("checkpoint.json"), "").unwrap();
    assert_eq!(latest_checkpoint(run.path()), None);
    let (ten, twenty) = (write(&root, 10), write(&root, 20));
    std::fs::create_dir_all(root.join("ep000030")).unwrap(); // no checkpoint.json: not complete
    assert_eq!(latest_checkpoint(run.path()), Some(twenty.clone()));
    assert_eq!(checkpoint_folders(&root), vec![ten, twenty]);
    // A resume gives the staging folder's space back.
    recover_folders(&root).unwrap();
    assert!(!staging.exists());
}

/// Finding 10: with ep1000000 present, ep999999 sorted last as text
/// and was resumed (and pruning deleted the newest).
#[test]
fn checkpoints_are_ordered_by_episode_not_by_name() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    for episode in [999_998, 1_000_001, 999_999, 1_000_000] {
        write(&root, episode);
    }
    assert_eq!(latest_checkpoint(run.path()), Some(root.join("ep1000001")));
    prune_checkpoints(&root, 3);
    assert_eq!(names(&root), ["ep1000000", "ep1000001", "ep999999"]);
    assert_eq!(checkpoint_episode("ep+5"), None);
    assert_eq!(checkpoint_episode("ep"), None);
}

/// Pruning counts intact checkpoints: two damaged newer folders do not
/// push the last good ones out (resume would then find none).
#[test]
fn pruning_keeps_the_newest_intact_checkpoints() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    for episode in [10, 20, 30, 40, 50, 60] {
        write(&root, episode);
    }
    for damaged in [50, 60] {
        std::fs::write(root.join(format!("ep{damaged:06}")).join("checkpoint.json"), "{").unwrap();
    }
    prune_checkpoints(&root, 3);
    assert_eq!(names(&root), ["ep000020", "ep000030", "ep000040", "ep000050", "ep000060"]);
    assert_eq!(latest_checkpoint(run.path()), Some(root.join("ep000040")));
}

/// Finding 8: with the newest checkpoint truncated or garbled, resume
/// failed although the previous one was whole.
#[test]
fn a_damaged_newest_checkpoint_is_skipped_for_the_previous_one() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    let ten = write(&root, 10);
    let twenty = write(&root, 20);
    check_intact(&twenty).unwrap();
    let json = twenty.join("checkpoint.json");
    let text = std::fs::read_to_string(&json).unwrap();
    assert!(text.contains("\"files\"") && text.contains("\"actor.safetensors\""), "{text}");
    let damage: [(&str, Vec<u8>); 5] = [
        ("checkpoint.json", text.as_bytes()[..text.len() / 2].to_vec()),
        ("checkpoint.json", b"garbage".to_vec()),
        ("actor.safetensors", tensors()[..tensors().len() - 2].to_vec()),
        ("actor.safetensors", b"\xff\xff\xff\xff\xff\xff\xff\xffjunk".to_vec()),
        ("agent.json", b"{\"tag\":".to_vec()),
    ];
    for (file, bytes) in damage {
        let whole = std::fs::read(twenty.join(file)).unwrap();
        std::fs::write(twenty.join(file), &bytes).unwrap();
        assert!(check_intact(&twenty).is_err(), "{file} damaged");
        assert_eq!(latest_checkpoint(run.path()), Some(ten.clone()), "{file} damaged");
        std::fs::write(twenty.join(file), whole).unwrap();
    }
    // A file the manifest lists is gone; then the same size but the
    // tensors' header no longer matching the length.
    std::fs::remove_file(twenty.join("agent.json")).unwrap();
    assert_eq!(latest_checkpoint(run.path()), Some(ten.clone()));
    // A checkpoint written before the manifest: the tensors' headers
    // still tell a file cut short or grown.
    std::fs::write(ten.join("checkpoint.json"), serde_json::to_string(&meta(10)).unwrap()).unwrap();
    check_intact(&ten).unwrap();
    let mut longer = tensors();
    longer.push(0);
    std::fs::write(ten.join("actor.safetensors"), longer).unwrap();
    assert!(check_intact(&ten).is_err());
    std::fs::write(ten.join("actor.safetensors"), &tensors()[..10]).unwrap();
    assert!(check_intact(&ten).is_err());
    assert_eq!(latest_checkpoint(run.path()), None);
}

/// Finding 9: a full disk at a checkpoint left its `.partial` folder
/// taking the space. The fill's error stands for ENOSPC.
#[test]
fn a_failed_fill_leaves_no_staging_folder_and_the_old_folder_whole() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    let target = write(&root, 10);
    let full = |staging: &Path| {
        std::fs::write(staging.join("actor.safetensors"), b"half").map_err(io(staging))?;
        Err(LearnerError::Io { path: staging.join("critic.safetensors"), source: std::io::Error::from_raw_os_error(28) })
    };
    let err = write_folder(&target, &meta(10), full).unwrap_err();
    assert!(err.to_string().contains("No space left"), "{err}");
    assert_eq!(names(&root), ["ep000010"]);
    check_intact(&target).unwrap();
    assert_eq!(std::fs::read_to_string(target.join("agent.json")).unwrap(), r#"{"tag":"first"}"#);
    // A new folder that fails leaves nothing at all.
    assert!(write_folder(&root.join("ep000020"), &meta(20), full).is_err());
    assert_eq!(names(&root), ["ep000010"]);
    // Replacing works, and leaves nothing beside the folder.
    write_folder(&target, &meta(10), fill("second")).unwrap();
    assert_eq!(names(&root), ["ep000010"]);
    assert_eq!(std::fs::read_to_string(target.join("agent.json")).unwrap(), r#"{"tag":"second"}"#);
}

/// Finding 8: the old folder was deleted before the new one was renamed
/// in. Now a kill between the two renames leaves `.NAME.old`, which is
/// resumed from and put back.
#[test]
fn an_interrupted_swap_still_resumes_from_a_whole_folder() {
    let run = tempfile::tempdir().unwrap();
    let root = run.path().join("checkpoints");
    write(&root, 10);
    let twenty = write(&root, 20);
    let aside = root.join(".ep000020.old");
    // Killed between the renames: the old folder aside, the new one
    // still staged (here only partly written).
    std::fs::rename(&twenty, &aside).unwrap();
    std::fs::create_dir_all(root.join(".ep000020.partial")).unwrap();
    std::fs::write(root.join(".ep000020.partial/actor.safetensors"), b"ha").unwrap();
    assert_eq!(latest_checkpoint(run.path()), Some(aside.clone()));
    recover_folders(&root).unwrap();
    assert_eq!(names(&root), ["ep000010", "ep000020"]);
    assert_eq!(latest_checkpoint(run.path()), Some(twenty.clone()));
    // Killed after the swap, before the old folder was deleted: the
    // new folder is the checkpoint, the old one goes.
    std::fs::create_dir_all(&aside).unwrap();
    assert_eq!(latest_checkpoint(run.path()), Some(twenty.clone()));
    assert_eq!(checkpoint_folders(&root).len(), 2);
    recover_folders(&root).unwrap();
    assert_eq!(names(&root), ["ep000010", "ep000020"]);
    // The next write of the folder recovers on its own too.
    std::fs::rename(&twenty, &aside).unwrap();
    write_folder(&twenty, &meta(20), fill("second")).unwrap();
    assert_eq!(names(&root), ["ep000010", "ep000020"]);
    assert_eq!(std::fs::read_to_string(twenty.join("agent.json")).unwrap(), r#"{"tag":"second"}"#);
}
