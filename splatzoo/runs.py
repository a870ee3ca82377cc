"""Run folders: the one place that creates, resumes, locks, loads and evaluates a training run. Commands (train, eval,
render, compare, sweep, extract-mesh, export, the viewer) go through here; the names below live in four modules:

  run_folder   the folder (config.json, checkpoint.pt, model.pt, model.szp, train_log.jsonl, metrics.json, renders/,
               the lock): what made a run and its fingerprints, status, lock, --overwrite, loading; run folders as a
               model file format (splatzoo.model_files)
  run_launch   a training launch: the request checked against the folder, a new run made or an interrupted one
               resumed with its state checked, the loop with its log and checkpoints, torchrun's ranks
  run_spawn    --nproc: ranks spawned on this machine and their heartbeats
  run_eval     evaluation and renders of a finished run, or of a model file on a dataset named with it
"""
from .run_eval import evaluate_file, evaluate_run, load_run, render_file, render_run  # noqa: F401
from .run_folder import (LOCK_NAME, REPLACED_NAME, RUN_ENTRIES, RUN_FORMAT, SCENE_OPTION_DEFAULTS,  # noqa: F401
                         TRAINING_CODE, Run, RunLockedError, TrainingInterrupted, TrainResult, code_fingerprint,
                         differences, load_options, made_by_other_code, make_record, normalize_scene_options,
                         scene_fingerprint)
from .run_launch import initial_model, train  # noqa: F401
from .run_spawn import HEARTBEAT_S, RANK_TIMEOUT_S, loopback_interface  # noqa: F401
