"""The session file's data model (pydantic): dataset, camera, settings, selection, annotations, review
state; the session's file names and errors.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

from ..camera import CameraIntrinsics
from ..crops import DEFAULT_CROP

SESSION_FILE = "session.json"
JOURNAL_FILE = "journal.jsonl"
CROPS_FILE = "crops.npy"
CROPS_META_FILE = "crops_meta.npz"
LOCK_FILE = "session.lock"


class SessionError(RuntimeError):
    """A session folder is missing, corrupt or cannot be written. The message names the file."""


class SessionLockedError(SessionError):
    """Another process (named in the message by PID and command) is writing this session."""


# ---------------------------------------------------------------------------------------------
# The persistent model


class DatasetSpec(BaseModel):
    path: str
    format: str
    intrinsics: CameraIntrinsics | None = None
    depth_scale_mm: float | None = None


class Settings(BaseModel):
    cube_mm: float = DEFAULT_CROP.cube_mm
    crop_size: int = DEFAULT_CROP.size
    descriptor: str = "downsampled"
    eps_mm: float = 15.0
    angle_limits: bool = True
    aligner: str = "dis"
    #: refit the lifted references with the personalized hand model (``lift.model_refit``)
    lift_refit: bool = True
    #: the annotators' click noise (px) the refit trusts the clicks by; None: estimated per lift
    click_noise_px: float | None = None
    #: where the click noise (given or estimated) is at least this many px, the lift tries a second
    #: bone estimate (shrunk, from the clicks moved towards the refit's joints) and keeps it where
    #: the hand model explains the references' depth better (``pipeline._bones_from_denoised_
    #: clicks``); None: never. Exact clicks on the tune part's FPHA hands are estimated at up to
    #: 0.81 px (the model's own misfit); chosen on the tune part (README, "Stop 29: bone lengths
    #: from noisy clicks")
    lift_denoise_min_px: float | None = 1.0
    #: fit the personalized hand model to every frame in propagation and refinement (issue 13; on
    #: since it lowers the mean on every tune sequence and raises no max by more than 2 mm, README;
    #: ``handanno propagate/refine --model/--no-model`` override it per call). Sessions written
    #: before the setting existed read it as on.
    hand_model: bool = True


class SelectionModel(BaseModel):
    strategy: str | None = None
    reference_frames: list[int] = Field(default_factory=list)
    parent: list[int] = Field(default_factory=list)
    threshold: float | None = None
    ref_fraction: float | None = None
    #: frames the selection could not use (unreadable, or no hand pixels): never references
    skipped_frames: list[int] = Field(default_factory=list)


class SessionModel(BaseModel):
    version: int = 1
    name: str
    dataset: DatasetSpec
    frames: int
    camera: CameraIntrinsics
    skeleton: str = "msra21"
    sequence_breaks: list[int] = Field(default_factory=list)
    settings: Settings = Field(default_factory=Settings)
    selection: SelectionModel = Field(default_factory=SelectionModel)
    #: frame index (as a string key) -> FrameAnnotation.to_json()
    annotations: dict[str, dict[str, Any]] = Field(default_factory=dict)
    #: the session's bone lengths: the lift's estimate for a one-hand session; with several hands
    #: the mean over the hands' lengths (what the app shows; stages use ``hand_bone_lengths_mm``)
    bone_lengths_mm: list[float] | None = None
    bones_pinned: bool = False
    #: the annotators' click noise (px) the last lift's refit used: estimated from the clicks
    #: (``lift_click_noise_given`` False) or given; None before a lift with the refit
    lift_click_noise_px: float | None = None
    lift_click_noise_given: bool = False
    #: one hand label per sequence (``len(sequence_breaks) + 1`` entries): sequences with the same
    #: label are one person's hand and share bone lengths; empty = one hand for the whole session
    hands: list[str] = Field(default_factory=list)
    #: hand label -> its bone lengths (mm), from the lift (several hands only; else empty)
    hand_bone_lengths_mm: dict[str, list[float]] = Field(default_factory=dict)
    #: frame -> "accepted" | "flagged"
    review: dict[str, str] = Field(default_factory=dict)
    #: frames that became references through review corrections (annotation cost beyond the selection)
    corrections: list[int] = Field(default_factory=list)
    journal_seq: int = 0
    #: random id of this session, part of every journal entry's checksum (so an entry copied from
    #: another session's journal is refused); empty in sessions made before journal checksums.
    session_id: str = ""
