use super::load::{LTI_FAST, PEG};
use super::*;
use std::path::Path;

/// `[controller] base = …`, the deprecated name of `[base] action = …`,
/// still loads, to the same config, from a file, through overrides laid
/// over an environment's settings, and from a checkpoint's JSON; both
/// at once are refused.
#[test]
fn the_deprecated_controller_table_still_loads() {
    let new: TrainConfig = toml::from_str("[base]\naction = \"a = 0\"\n").unwrap();
    let old: TrainConfig = toml::from_str("[controller]\nbase = \"a = 0\"\n").unwrap();
    assert_eq!(new, old);
    assert_eq!(new.base.action, BaseController::Zero);
    let overrides = |text: &str| TrainConfig::for_env_with("peg-group1", &toml::from_str(text).unwrap()).unwrap();
    let (new, old) = (overrides("[base]\naction = \"a = 0\"\n"), overrides("[controller]\nbase = \"a = 0\"\n"));
    assert_eq!(new, old);
    assert_eq!(old.base.action, BaseController::Zero, "the override wins over peg.toml's best constant");
    let json = serde_json::to_value(&new).unwrap();
    let mut legacy = json.as_object().unwrap().clone();
    let base = legacy.remove("base").unwrap();
    legacy.insert("controller".into(), serde_json::json!({ "base": base["action"] }));
    assert_eq!(serde_json::from_value::<TrainConfig>(serde_json::Value::Object(legacy)).unwrap(), new);
    let both = toml::from_str::<TrainConfig>("[base]\naction = \"none\"\n[controller]\nbase = \"a = 0\"\n").unwrap_err().to_string();
    assert!(both.contains("both [base] and [controller]"), "{both}");
}

#[test]
fn defaults_follow_table_1_and_validate() {
    let cfg = TrainConfig::default();
    cfg.validate().unwrap();
    assert_eq!((cfg.ddpg.actor_lr, cfg.ddpg.critic_lr, cfg.ddpg.tau), (1e-3, 1e-2, 1e-3));
    assert_eq!((cfg.ppo.actor_lr, cfg.ppo.critic_lr), (1e-4, 1e-3));
}

#[test]
fn registered_environments_get_their_working_settings() {
    let (lti, source) = TrainConfig::for_env("lti-paper");
    assert!(source.contains("lti-fast"), "{source}");
    let file: TrainConfig = toml::from_str(LTI_FAST).unwrap();
    assert_eq!(lti, file);
    lti.validate().unwrap();
    assert_eq!(lti.run.episodes, 1000, "lti-fast.toml's budget is 1000 episodes");
    assert_eq!(lti.network.activation, Activation::Elu);
    let peg: TrainConfig = toml::from_str(PEG).unwrap();
    peg.validate().unwrap();
    // peg-group2: peg.toml with the trust region at 1, the critic's head
    // start and DDPG's reach at 0.875, nothing else.
    let (group2, source) = TrainConfig::for_env("peg-group2");
    assert!(source.contains("configs/peg-group2.toml"), "{source}");
    group2.validate().unwrap();
    assert_eq!((group2.ddpg.proximal_l2, group2.ddpg.critic_warmup_updates, group2.ddpg.residual_scale), (1.0, 2000, Some(0.875)));
    let ddpg = DdpgConfig { proximal_l2: 0.0, critic_warmup_updates: 0, residual_scale: None, ..group2.ddpg.clone() };
    assert_eq!(TrainConfig { ddpg, ..group2 }, peg, "peg-group2.toml changes only [ddpg] proximal_l2, critic_warmup_updates and residual_scale");
    // A noisy preset is its group with a sensor: the group's settings.
    assert_eq!(TrainConfig::for_env("peg-group2-noisy"), TrainConfig::for_env("peg-group2"));
    assert_eq!(TrainConfig::for_env("peg-group1-noisy"), TrainConfig::for_env("peg-group1"));
    // peg-group1: peg.toml with the trust region, nothing else.
    let (group1, source) = TrainConfig::for_env("peg-group1");
    assert!(source.contains("configs/peg-group1.toml"), "{source}");
    group1.validate().unwrap();
    assert_eq!((group1.ddpg.proximal_l2, peg.ddpg.proximal_l2), (3.0, 0.0));
    let ddpg = DdpgConfig { proximal_l2: 0.0, ..group1.ddpg.clone() };
    assert_eq!(TrainConfig { ddpg, ..group1 }, peg, "peg-group1.toml changes only [ddpg] proximal_l2");
    // The randomized presets: peg.toml with the residual penalty, nothing else.
    for name in ["peg-group1-rand", "peg-group2-rand"] {
        let (rand, source) = TrainConfig::for_env(name);
        assert!(source.contains("configs/peg-rand.toml"), "{source}");
        rand.validate().unwrap();
        assert_eq!((rand.ddpg.critic_warmup_updates, rand.ddpg.preactivation_l2), (0, 10.0), "{name}");
        let ddpg = DdpgConfig { preactivation_l2: peg.ddpg.preactivation_l2, ..rand.ddpg.clone() };
        assert_eq!(TrainConfig { ddpg, ..rand }, peg, "peg-rand.toml changes only [ddpg] preactivation_l2 ({name})");
    }
    // peg-experiment: peg.toml with its own DDPG keys over it, nothing else.
    let (experiment, source) = TrainConfig::for_env("peg-experiment");
    assert!(source.contains("configs/peg-experiment.toml"), "{source}");
    experiment.validate().unwrap();
    assert_eq!((experiment.ddpg.critic_warmup_updates, experiment.ddpg.preactivation_l2), (5000, 10.0));
    let with_peg_ddpg = TrainConfig { ddpg: peg.ddpg.clone(), ..experiment.clone() };
    assert_eq!(with_peg_ddpg, peg, "peg-experiment.toml changes only [ddpg]");
    assert_eq!(TrainConfig::for_env("grpc://127.0.0.1:1").0, TrainConfig::default());
}

/// The named Table I files hold exactly the publication's settings
/// (the defaults of this file), whatever environment they are laid
/// over: a study can put them beside the working settings.
#[test]
fn table1_files_are_table1_over_any_environment() {
    for name in ["table1-ddpg.toml", "table1-ppo.toml"] {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs").join(name);
        for env in ["peg-group1", "lti-paper"] {
            let cfg = TrainConfig::load_for_env(&path, env).unwrap();
            let table1 = TrainConfig::default();
            if name.contains("ddpg") {
                assert_eq!((&cfg.ddpg, &cfg.network, &cfg.base), (&table1.ddpg, &table1.network, &table1.base), "{name} over {env}");
            } else {
                assert_eq!((&cfg.ppo, &cfg.network, &cfg.base), (&table1.ppo, &table1.network, &table1.base), "{name} over {env}");
            }
        }
    }
}

#[test]
fn bad_values_name_the_field() {
    let err = |text: &str| -> String {
        match toml::from_str::<TrainConfig>(text).map_err(|e| e.to_string()).and_then(|c| c.validate().map_err(|e| e.to_string())) {
            Err(e) => e,
            Ok(()) => panic!("accepted {text}"),
        }
    };
    assert!(err("[ddpg]\nactor_lr = -0.001\n").contains("ddpg.actor_lr"));
    assert!(err("[ppo]\ngamma = 1.5\n").contains("ppo.gamma"));
    assert!(err("[network]\nsubnet_hidden = []\n").contains("network.subnet_hidden"));
    assert!(err("[run]\ndevice = \"tpu\"\n").contains("run.device"));
    assert!(err("[ddpg]\nactor_rate = 0.1\n").contains("actor_rate"));
    assert!(err("[run]\nconfirm_candidates = 3\n").contains("`run.confirm_candidates` needs validation"));
    assert!(err("[run]\nvalidation_episodes = 30\nconfirm_candidates = 3\nconfirm_episodes = 0\n").contains("run.confirm_episodes"));
    assert!(err("[base]\naction = \"best-constant\"\nresidual_scale = 0.0\n").contains("base.residual_scale"));
    assert!(err("[base]\naction = \"best-constant\"\nresidual_scale = 1.5\n").contains("base.residual_scale"));
    assert!(err("[base]\nresidual_scale = 0.5\n").contains("needs a base controller"));
    assert!(err("[base]\naction = \"best-constant\"\n[ddpg]\nresidual_scale = 0.0\n").contains("ddpg.residual_scale"));
    assert!(err("[base]\naction = \"best-constant\"\n[ddpg]\nresidual_scale = 1.5\n").contains("ddpg.residual_scale"));
    assert!(err("[ddpg]\nresidual_scale = 0.5\n").contains("`ddpg.residual_scale` needs a base controller"));
}

/// DDPG's own reach: peg-group2's is 0.875 for DDPG and the whole box for
/// PPO; a reach in `[base]`, or a base other than the best constant, laid
/// over the preset replaces it, `[ddpg] residual_scale` sets it; and a
/// run's resolved settings, read back as overrides, resolve to themselves.
#[test]
fn ddpg_reach_is_ddpg_alone_and_a_users_base_replaces_it() {
    let reaches = |text: &str| {
        let cfg = TrainConfig::for_env_with("peg-group2", &toml::from_str(text).unwrap()).unwrap();
        let again = TrainConfig::for_env_with("peg-group2", &toml::Table::try_from(&cfg).unwrap()).unwrap();
        assert_eq!(again, cfg, "{text:?} read back from its resolved settings");
        (cfg.residual_scale(Algo::Ddpg), cfg.residual_scale(Algo::Ppo))
    };
    assert_eq!(reaches(""), (0.875, 1.0));
    assert_eq!(reaches("[base]\naction = \"best-constant\"\n"), (0.875, 1.0), "the preset's own base keeps its reach");
    assert_eq!(reaches("[run]\nseed = 3\n"), (0.875, 1.0));
    assert_eq!(reaches("[base]\nresidual_scale = 0.75\n"), (0.75, 0.75), "configs/peg-safe.toml's reach binds both");
    assert_eq!(reaches("[base]\nresidual_scale = 1.0\n"), (1.0, 1.0), "the whole box asked for in [base], though [base] does not write it");
    assert_eq!(reaches("[base]\naction = \"a = 0\"\n"), (1.0, 1.0), "from scratch the whole box, as measured");
    assert_eq!(reaches("[base]\naction = \"none\"\n"), (1.0, 1.0), "no base, no reach to scale");
    assert_eq!(reaches("[ddpg]\nresidual_scale = 0.5\n"), (0.5, 1.0));
    assert_eq!(reaches("[base]\nresidual_scale = 0.75\n[ddpg]\nresidual_scale = 0.5\n"), (0.5, 0.75));
    // A recorded base of numbers (config.toml of a run) with no DDPG reach
    // is a run from before it: it keeps the reach it ran with.
    assert_eq!(reaches("[base]\naction = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n"), (1.0, 1.0));
    // Environments without a DDPG reach: [base] for both.
    let group1 = TrainConfig::for_env("peg-group1").0;
    assert_eq!((group1.residual_scale(Algo::Ddpg), group1.residual_scale(Algo::Ppo)), (1.0, 1.0));
}

/// Files written before an option was removed (a checkpoint's config, a
/// study's resolved config) hold it at its "off" value: they read as
/// before. Any other value is refused as the unknown key it now is.
#[test]
fn removed_options_read_at_their_off_value_only() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("old.toml");
    std::fs::write(&file, "[ddpg]\nwarmup_actions = \"uniform\"\nactor_lr_warmup_updates = 0\ncritic_disagreement = 0.0\ntemporal_smoothness = 0.0\nbatch_size = 32\n").unwrap();
    assert_eq!(TrainConfig::load(&file).unwrap().ddpg.batch_size, 32);
    for (text, key) in [("warmup_actions = \"policy\"", "warmup_actions"), ("temporal_smoothness = 1.0", "temporal_smoothness"), ("actor_lr_warmup_updates = 5", "actor_lr_warmup_updates")] {
        std::fs::write(&file, format!("[ddpg]\n{text}\n")).unwrap();
        let err = TrainConfig::load(&file).unwrap_err().to_string();
        assert!(err.contains(key), "{err}");
    }
    let mut json = serde_json::to_value(TrainConfig::default()).unwrap();
    json["ddpg"]["warmup_actions"] = "uniform".into();
    json["ddpg"]["critic_disagreement"] = 0.0.into();
    let mut kept = json.clone();
    crate::config::drop_removed_json_keys_at_off(&mut kept);
    assert_eq!(serde_json::from_value::<TrainConfig>(kept).unwrap(), TrainConfig::default());
    json["ddpg"]["critic_disagreement"] = 1.0.into();
    crate::config::drop_removed_json_keys_at_off(&mut json);
    assert!(serde_json::from_value::<TrainConfig>(json).unwrap_err().to_string().contains("critic_disagreement"));
}
