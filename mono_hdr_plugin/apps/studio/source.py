"""The studio as a scene source: `--scene NAME` for every built-in scene (entry point `studio`)."""

from mono_hdr_plugin.apps.studio.scenes import SCENES
from mono_hdr_plugin.data.captures import CapturedScene
from mono_hdr_plugin.data.sources import SceneSource


class StudioScenes(SceneSource):
    """Built-in Mitsuba scenes, rendered once (cached) and photographed by the capture simulator."""

    def names(self) -> list[str]:
        return list(SCENES)

    def captured_scene(self, name: str, seed: int, resolution: int | None = None) -> CapturedScene:
        from mono_hdr_plugin.apps.studio.dataset import get_scene, studio_captured_scene

        return studio_captured_scene(get_scene(name, resolution), seed=seed)


STUDIO_SCENES = StudioScenes()
