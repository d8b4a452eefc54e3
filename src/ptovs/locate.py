"""Scene resolution: which folder a command's --scene and --data name.

A scene is a folder under the data folder (`data/<scene>`, or
`$PTOVS_DATA/<scene>`), or the folder given as --data; its artifacts go to
`<work>/<scene>/`. A folder that is part of a scene (`dense/`, `images/`, a COLMAP
model) is refused with the scene folder to pass instead. A folder of unposed
photos is posed first by the `sfm` stage (`ptovs.sfm`, cached under
`<work>/<scene>/sfm/`), and the posed scene is what the chain reads. The
`[scene]` and `[sfm]` options come from the scene's resolved settings
(`ptovs.settings`), which the caller passes down.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import click

from ptovs.chain import SceneRef
from ptovs.errors import InputError, MissingInputError
from ptovs.registry import SCENE, SFM
from ptovs.settings import RunContext, Settings, resolve_settings

log = logging.getLogger(__name__)


def _scene_name(name: str, data: Path | None) -> tuple[str, Path | None]:
    """`--scene` is a name: it names the scene's folder under the work dir, so a
    path there would write outside it. A path to a folder given without --data is
    taken as --data (the scene named by the folder); anything else with a path
    separator, or "." / "..", is refused with the command to use."""
    if name and "/" not in name and "\\" not in name and name not in (".", ".."):
        return name, data
    path = Path(name).expanduser()
    if data is None and path.is_dir():
        resolved = path.resolve()
        log.info("--scene %s is a folder: taken as --data %s (scene %s)",
                 name, path, resolved.name)  # fmt: skip
        return resolved.name, path
    hint = Path(name).name or "myscene"
    raise InputError(
        f"--scene takes a name, not a path ({name!r}); give the folder as --data: "
        f"--data {name} [--scene {hint}]"
    )


def scene_part(path: Path) -> tuple[Path, str] | None:
    """(the scene folder, what `path` is in it) when `path` is a folder inside a
    scene rather than the scene: PhotoTourism's `dense/`, a scene's `images/` or
    `sparse/` (or a model `sparse/N`). Given as --data, such a folder would become a
    scene named "dense" or "images" that has lost its split and labels."""
    p = Path(path).resolve()
    if not p.is_dir():
        return None
    if p.name == "dense" and (p / "images").is_dir():
        return p.parent, "dense/ folder"
    if p.name in ("images", "sparse"):
        up = p.parent
        if up.name == "dense" and (up / "sparse").is_dir():
            return up.parent, f"dense/{p.name}/ folder"
        return up, f"{p.name}/ folder"  # the scene (or photo collection) holds it
    if p.parent.name == "sparse" and any(
        (p / f"cameras.{ext}").is_file() for ext in ("bin", "txt")
    ):
        up = p.parent.parent
        root = up.parent if up.name == "dense" else up
        return root, f"COLMAP model {p.relative_to(root)}/"
    return None


def scene_source(
    scene_name: str | None, data: Path | None
) -> tuple[str, Path, Path | None]:
    """(scene name, --data folder, its photo folder if it holds unposed photos)."""
    if scene_name is None and data is None:
        raise click.UsageError("give --scene NAME and/or --data FOLDER")
    if scene_name is not None:
        scene_name, data = _scene_name(scene_name, data)
    if data is None:
        data = Path(os.environ.get("PTOVS_DATA", "data")) / scene_name
    part = scene_part(Path(data))
    if part is not None:
        root, what = part
        shown = os.path.relpath(root) if not Path(data).is_absolute() else str(root)
        raise InputError(
            f"--data {data} is the {what} of the scene folder {shown}, not a scene: "
            f"pass --data {shown}" + (f" --scene {scene_name}" if scene_name else "")
        )
    if scene_name is None:
        scene_name = Path(data).resolve().name
    if not Path(data).is_dir():
        raise MissingInputError(
            f"scene folder {data} does not exist; pass --data pointing at a scene "
            "(PhotoTourism: <scene>/dense/images + dense/sparse; COLMAP: images/ + sparse/0), "
            "or make one with: ptovs synth-scene data --preset tiny"
        )
    from ptovs.sfm import photo_dir

    return scene_name, Path(data), photo_dir(Path(data))


def pose_photos(
    settings: Settings, scene_name: str, photos: Path, *, run: bool, force: bool = False
) -> tuple[str, str, Path]:
    """(key, state, posed scene folder) of the `sfm` stage for a photo folder, with
    the scene's `[sfm]` settings: run (cached, under its lock) if `run`, else only
    looked up (`ptovs status`)."""
    from ptovs.keys import flush_fingerprints
    from ptovs.sfm import posed_scene, sfm_location, sfm_state

    config = settings.build(SFM)
    if not run:
        return sfm_state(photos, scene_name, settings.work_dir, config)
    out = posed_scene(photos, scene_name, settings.work_dir, config, force=force)
    flush_fingerprints()  # SfM ran: the scene's config is recorded, as a stage's
    return sfm_location(photos, scene_name, settings.work_dir, config)[1], "done", out


def scene_ref(
    settings: Settings,
    scene_name: str,
    data: Path,
    photos: Path | None,
    before_sfm: Callable[[Settings], None] | None = None,
) -> SceneRef:
    """The scene `scene_source` found, read with its settings' `[scene]`. A folder
    of unposed photos is posed first by the `sfm` stage (cached);
    `before_sfm(settings)` runs first when SfM has still to run (the command's
    preflight checks that need no scene)."""
    source = data  # what the user gave: advice names it, not the posed copy
    if photos is not None:  # unposed photos: SfM first (cached), then a COLMAP scene
        if before_sfm is not None:
            from ptovs.keys import read_only

            with read_only():  # the state lookup writes no cache
                state = pose_photos(settings, scene_name, photos, run=False)[1]
            if state != "done":
                before_sfm(settings)
        data = pose_photos(settings, scene_name, photos, run=True)[2]
    return SceneRef(scene_name, Path(data), settings.build(SCENE), settings.work_dir,
                    source)  # fmt: skip


def resolve_scene(
    ctx: RunContext | Settings, scene_name: str | None, data: Path | None
) -> SceneRef:
    """The scene a command works on (`scene_source`), read with its settings
    (`ctx`'s resolved for it, `ptovs.settings.resolve_settings`, unless `ctx` is
    them already)."""
    scene_name, data, photos = scene_source(scene_name, data)
    settings = ctx if isinstance(ctx, Settings) else resolve_settings(ctx, scene_name)
    return scene_ref(settings, scene_name, data, photos)
