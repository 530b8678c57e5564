"""The procedural scenes: layout, materials, camera rig and edit vocabulary of `tiny` and `campsite`.

World axes: z up, metres, ground at z = 0, scene centre at the origin. The background is a textured dome
(distant hills, sky and clouds) at finite distance, so SfM finds points on it and the normalisation to
[-1, 1]^3 bounds everything a NeRF has to model.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualnerf.scenes.geometry import (
    Cylinder,
    Disk,
    Dome,
    Ellipsoid,
    box,
    prism_tent,
    pyramid,
    rotation_y,
    rotation_z,
)
from dualnerf.scenes.materials import Material
from dualnerf.scenes.render import SceneObject, Variant, World


@dataclass(frozen=True)
class EditDef:
    id: str
    instruction: str
    source_caption: str
    target_caption: str
    variant: Variant


@dataclass(frozen=True)
class SceneConfig:
    name: str
    width: int
    height: int
    n_views: int
    arc_degrees: float          # 360 = full circle
    camera_radius: float
    camera_height: float
    height_wobble: float
    fov_degrees: float          # horizontal field of view
    supersample: int
    dome_radius: float
    target_height: float = 0.5
    mask_threshold: int = 3     # max |edited - original| over channels (8-bit) that still counts as unchanged

    @property
    def focal(self) -> float:
        return 0.5 * self.width / np.tan(np.deg2rad(self.fov_degrees) / 2)


# Materials (palettes are display RGB in [0, 1]).
GRASS = Material("grass", ((0.30, 0.45, 0.16), (0.45, 0.50, 0.22), (0.42, 0.33, 0.22)),
                 frequency=0.35, octaves=8, patch_amount=0.5, detail=0.45)
TENT = Material("tent", ((0.85, 0.38, 0.10), (0.72, 0.25, 0.08), (0.95, 0.62, 0.20)),
                frequency=0.8, octaves=6, patch_amount=0.2, detail=0.3)
TENT_BLUE = ((0.12, 0.30, 0.80), (0.08, 0.20, 0.62), (0.25, 0.50, 0.92))
WOOD = Material("wood", ((0.62, 0.45, 0.26), (0.50, 0.34, 0.18), (0.40, 0.27, 0.14)),
                pattern="planks", frequency=1.5, octaves=5, patch_amount=0.1, detail=0.3)
BARK = Material("bark", ((0.36, 0.25, 0.16), (0.27, 0.18, 0.11), (0.45, 0.35, 0.24)),
                frequency=3.0, octaves=5, patch_amount=0.3, detail=0.5)
ROCK = Material("rock", ((0.52, 0.52, 0.50), (0.40, 0.40, 0.40), (0.62, 0.60, 0.55)),
                frequency=1.5, octaves=6, patch_amount=0.4, detail=0.5)
COOLER = Material("cooler", ((0.10, 0.55, 0.60), (0.08, 0.45, 0.50), (0.90, 0.90, 0.88)),
                  frequency=1.2, octaves=5, patch_amount=0.15, detail=0.25)
FOLIAGE = Material("foliage", ((0.14, 0.36, 0.14), (0.22, 0.45, 0.18), (0.10, 0.26, 0.10)),
                   frequency=1.2, octaves=6, patch_amount=0.4, detail=0.5)
SKY = Material("sky", ((0.20, 0.30, 0.18), (0.42, 0.62, 0.88), (0.95, 0.95, 0.97)),
               pattern="sky", frequency=0.6, octaves=7, emissive=True)

AUTUMN_FOLIAGE = ((0.80, 0.42, 0.08), (0.70, 0.22, 0.06), (0.90, 0.68, 0.12))
AUTUMN_GRASS = ((0.55, 0.48, 0.22), (0.62, 0.50, 0.25), (0.45, 0.32, 0.18))

SNOW_EDIT = EditDef("snow", "Make it look like it just snowed", "a campsite with a tent on grass",
                    "a campsite with a tent covered in fresh snow", Variant("snow", snow=True))
BLUE_TENT_EDIT = EditDef("blue_tent", "Turn the tent blue", "a campsite with an orange tent",
                         "a campsite with a blue tent", Variant("blue_tent", recolour={"tent": TENT_BLUE}))
AUTUMN_EDIT = EditDef("autumn", "Make it autumn", "a campsite with green trees in summer",
                      "a campsite with orange trees in autumn",
                      Variant("autumn", recolour={"foliage": AUTUMN_FOLIAGE, "grass": AUTUMN_GRASS}))


def _tree(name: str, x: float, y: float, height: float, conifer: bool) -> list[SceneObject]:
    trunk = SceneObject(f"{name}_trunk", Cylinder(centre=(x, y, 0.0), radius=0.12, height=height * 0.55), BARK)
    if conifer:
        crown = SceneObject(f"{name}_crown", pyramid((x, y, height * 0.3), radius=0.75, height=height * 0.8,
                                                     sides=9, angle=x), FOLIAGE)
    else:
        crown = SceneObject(f"{name}_crown", Ellipsoid(centre=(x, y, height * 0.7),
                                                       radii=(0.8, 0.75, 0.65)), FOLIAGE)
    return [trunk, crown]


def _log(name: str, centre, length: float, radius: float, yaw: float, material=BARK) -> SceneObject:
    # A cylinder along local z turned to lie along the ground, then yawed; centred on its length.
    rotation = rotation_z(yaw) @ rotation_y(np.pi / 2)
    axis = rotation[:, 2]
    start = np.asarray(centre, float) - axis * length / 2
    return SceneObject(name, Cylinder(centre=tuple(start), rotation=rotation, radius=radius, height=length),
                       material)


def _background(config: SceneConfig) -> list[SceneObject]:
    return [SceneObject("ground", Disk(radius=config.dome_radius), GRASS),
            SceneObject("sky", Dome(radius=config.dome_radius), SKY)]


def tiny_world(config: SceneConfig, seed: int) -> World:
    objects = [
        SceneObject("tent", prism_tent((0.0, 0.0, 0.0), length=1.8, width=1.5, height=1.1, angle=0.3), TENT),
        SceneObject("crate", box((1.3, -0.9, 0.3), (0.3, 0.3, 0.3), angle=0.4), WOOD),
        SceneObject("rock", Ellipsoid(centre=(-1.2, -1.0, 0.1), radii=(0.45, 0.35, 0.3)), ROCK),
        *_tree("tree", -1.0, 1.4, 2.2, conifer=True),
        *_background(config),
    ]
    return World(tuple(objects), seed=seed)


def campsite_world(config: SceneConfig, seed: int) -> World:
    objects = [
        SceneObject("tent", prism_tent((0.2, 0.6, 0.0), length=2.4, width=1.9, height=1.4, angle=0.35), TENT),
        SceneObject("crate", box((1.7, -0.4, 0.32), (0.32, 0.32, 0.32), angle=0.5), WOOD),
        SceneObject("crate_small", box((1.75, 0.25, 0.2), (0.25, 0.2, 0.2), angle=-0.2), WOOD),
        SceneObject("cooler", box((-1.5, 0.9, 0.25), (0.4, 0.25, 0.25), angle=-0.4), COOLER),
        SceneObject("rock_a", Ellipsoid(centre=(-1.8, -1.2, 0.12), radii=(0.5, 0.4, 0.35)), ROCK),
        SceneObject("rock_b", Ellipsoid(centre=(2.4, 1.7, 0.1), radii=(0.35, 0.45, 0.3)), ROCK),
        SceneObject("rock_c", Ellipsoid(centre=(-2.6, 0.2, 0.05), radii=(0.3, 0.3, 0.22)), ROCK),
        SceneObject("seat_log", _log("", (0.0, -2.1, 0.2), 1.8, 0.2, 0.15).primitive, BARK),
        *_tree("pine", -2.2, 2.4, 3.2, conifer=True),
        # Trees outside the camera circle: background with parallax, never between a camera and the camp.
        *_tree("oak", 8.3, -3.0, 3.4, conifer=False),
        *_tree("pine2", -4.0, -8.0, 4.2, conifer=True),
        *_tree("pine3", -8.6, 1.5, 3.8, conifer=True),
        *_tree("pine4", 3.5, 8.4, 4.0, conifer=True),
        *_background(config),
    ]
    # Campfire: a ring of stones around two crossed logs.
    fire_centre = np.array([-0.3, -1.0, 0.0])
    for i, a in enumerate(np.linspace(0, 2 * np.pi, 7, endpoint=False)):
        c = fire_centre + 0.42 * np.array([np.cos(a), np.sin(a), 0.0]) + [0, 0, 0.03]
        objects.append(SceneObject(f"fire_stone_{i}", Ellipsoid(centre=tuple(c), radii=(0.11, 0.09, 0.09)),
                                   ROCK))
    for i, yaw in enumerate((0.4, 2.0)):
        objects.append(_log(f"fire_log_{i}", fire_centre + [0, 0, 0.07 + 0.06 * i], 0.6, 0.06, yaw))
    return World(tuple(objects), seed=seed)


TINY = SceneConfig("tiny", width=160, height=120, n_views=26, arc_degrees=200.0, camera_radius=5.0,
                   camera_height=2.2, height_wobble=0.25, fov_degrees=60.0, supersample=2, dome_radius=9.0)
CAMPSITE = SceneConfig("campsite", width=256, height=192, n_views=48, arc_degrees=360.0, camera_radius=6.5,
                       camera_height=2.6, height_wobble=0.3, fov_degrees=60.0, supersample=2,
                       dome_radius=11.0)

BUILDERS = {"tiny": (tiny_world, (SNOW_EDIT, BLUE_TENT_EDIT)),
            "campsite": (campsite_world, (SNOW_EDIT, BLUE_TENT_EDIT, AUTUMN_EDIT))}
SCENES: dict[str, SceneConfig] = {"tiny": TINY, "campsite": CAMPSITE}
