"""The procedural scenes: layout, materials, camera rig and edit vocabulary of each scene.

    tiny       CI scene: a tent, a crate, a rock and a tree on a 200 degree arc
    campsite   outdoor 360 degree scene (a camp among trees)
    bear       object-centric 360 degree capture: a bear statue on a stone pedestal
    portrait   forward-facing capture: a head-and-shoulders figure before a hedge, on a frontal arc

Every edit also has alternative *modes* (`EditDef.modes`): other plausible appearances of the same
instruction (another blue for "turn the tent blue", grey overcast snow for "make it look like it just
snowed"), rendered by the same ray caster so they are as 3D-consistent as the ground truth. They are not
ground truth: the InstructPix2Pix emulator's mode lock-in (dualnerf.editors.emulator) draws its output
from them, and a field that ends in one of them has edited the scene the wrong way.

Every scene but `tiny` has the three kinds of edit (`EditDef.kind`): "recolour" (one object's
colours), "global" (season, weather or light over most of the image) and "geometry" (an object
added or removed, traced by the same ray caster so occlusion and shadows are exact).
`BUILDERS` / `SCENES` are the single list of scenes and their edits that other code iterates.

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

EDIT_KINDS = ("recolour", "global", "geometry")


@dataclass(frozen=True)
class EditDef:
    id: str
    instruction: str
    source_caption: str
    target_caption: str
    variant: Variant
    kind: str = "recolour"      # one of EDIT_KINDS
    modes: tuple[Variant, ...] = ()   # alternative appearances of the same instruction (not ground truth)


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

# Alternative modes (see the module docstring): another reading of the same instruction.
GREY_SNOW = (0.64, 0.68, 0.76)           # overcast, grey-blue snow instead of fresh white snow
TENT_TEAL = ((0.08, 0.52, 0.58), (0.05, 0.40, 0.46), (0.22, 0.68, 0.72))   # a teal "blue"
RED_FOLIAGE = ((0.70, 0.12, 0.08), (0.55, 0.08, 0.06), (0.82, 0.30, 0.10))  # red rather than orange leaves

SNOW_EDIT = EditDef("snow", "Make it look like it just snowed", "a campsite with a tent on grass",
                    "a campsite with a tent covered in fresh snow", Variant("snow", snow=True), kind="global",
                    modes=(Variant("grey_snow", snow=True, snow_colour=GREY_SNOW),))
BLUE_TENT_EDIT = EditDef("blue_tent", "Turn the tent blue", "a campsite with an orange tent",
                         "a campsite with a blue tent", Variant("blue_tent", recolour={"tent": TENT_BLUE}),
                         modes=(Variant("teal_tent", recolour={"tent": TENT_TEAL}),))
AUTUMN_EDIT = EditDef("autumn", "Make it autumn", "a campsite with green trees in summer",
                      "a campsite with orange trees in autumn",
                      Variant("autumn", recolour={"foliage": AUTUMN_FOLIAGE, "grass": AUTUMN_GRASS}),
                      kind="global",
                      modes=(Variant("red_autumn", recolour={"foliage": RED_FOLIAGE, "grass": AUTUMN_GRASS}),))


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


# --- campsite: a geometry edit (an added canoe; appended, so every other object keeps its texture) ---
CANOE = Material("canoe", ((0.78, 0.12, 0.10), (0.62, 0.08, 0.07), (0.90, 0.80, 0.70)),
                 frequency=1.4, octaves=5, patch_amount=0.15, detail=0.3)
CANOE_DARK = Material("canoe", ((0.45, 0.07, 0.09), (0.36, 0.05, 0.07), (0.62, 0.45, 0.35)),
                      frequency=1.4, octaves=5, patch_amount=0.15, detail=0.3)       # a maroon "red" canoe
_CANOE_SHAPE = Ellipsoid(centre=(2.3, -1.9, 0.06), radii=(1.0, 0.3, 0.2), rotation=rotation_z(0.8))
CANOE_EDIT = EditDef(
    "canoe", "Put a red canoe next to the campfire", "a campsite with a tent and a campfire",
    "a campsite with a tent, a campfire and a red canoe",
    Variant("canoe", add=(SceneObject("canoe", _CANOE_SHAPE, CANOE),)),
    kind="geometry", modes=(Variant("maroon_canoe", add=(SceneObject("canoe", _CANOE_SHAPE, CANOE_DARK),)),))

# --- bear: an object-centric 360 degree capture of a statue on a pedestal ---
FUR = Material("fur", ((0.42, 0.27, 0.15), (0.33, 0.20, 0.11), (0.55, 0.38, 0.22)),
               frequency=3.0, octaves=6, patch_amount=0.3, detail=0.45)
PAWS = Material("paws", ((0.25, 0.16, 0.09), (0.19, 0.12, 0.07), (0.34, 0.23, 0.13)),
                frequency=3.0, octaves=6, patch_amount=0.3, detail=0.45)
STONE = Material("stone", ((0.68, 0.66, 0.62), (0.55, 0.54, 0.52), (0.78, 0.74, 0.66)),
                 frequency=2.0, octaves=6, patch_amount=0.35, detail=0.5)
GRAVEL = Material("gravel", ((0.55, 0.50, 0.42), (0.42, 0.40, 0.36), (0.30, 0.42, 0.18)),
                  frequency=0.6, octaves=8, patch_amount=0.45, detail=0.5)
PARTY_HAT = Material("party_hat", ((0.90, 0.15, 0.45), (0.98, 0.80, 0.15), (0.20, 0.50, 0.90)),
                     frequency=6.0, octaves=4, patch_amount=0.4, detail=0.3)
PANDA_WHITE = ((0.90, 0.89, 0.86), (0.82, 0.81, 0.78), (0.95, 0.94, 0.92))
PANDA_BLACK = ((0.08, 0.08, 0.08), (0.13, 0.12, 0.12), (0.04, 0.04, 0.04))
WINTER_SKY = ((0.88, 0.90, 0.94), (0.62, 0.68, 0.78), (0.92, 0.92, 0.94))

PEDESTAL_TOP = 0.35
BEAR_HEAD = (0.62, 0.0, 1.02)

RED_PANDA_FUR = ((0.70, 0.30, 0.12), (0.60, 0.24, 0.09), (0.85, 0.55, 0.30))   # "panda" read as red panda
GREY_WINTER_SKY = ((0.70, 0.72, 0.75), (0.50, 0.53, 0.58), (0.80, 0.80, 0.82))
PARTY_HAT_GOLD = Material("party_hat", ((0.95, 0.75, 0.10), (0.15, 0.65, 0.30), (0.98, 0.95, 0.85)),
                          frequency=6.0, octaves=4, patch_amount=0.4, detail=0.3)
_PARTY_HAT_SHAPE = pyramid((BEAR_HEAD[0] - 0.03, 0.0, BEAR_HEAD[2] + 0.13), radius=0.14, height=0.42, sides=14)

PANDA_EDIT = EditDef("panda", "Turn the bear into a panda", "a statue of a brown bear on a stone pedestal",
                     "a statue of a black and white panda on a stone pedestal",
                     Variant("panda", recolour={"fur": PANDA_WHITE, "paws": PANDA_BLACK}), kind="recolour",
                     modes=(Variant("red_panda", recolour={"fur": RED_PANDA_FUR, "paws": PANDA_BLACK}),))
WINTER_EDIT = EditDef("winter", "Make it winter", "a bear statue in a gravel garden on a summer day",
                      "a bear statue in a snowy garden on a winter day",
                      Variant("winter", snow=True, recolour={"sky": WINTER_SKY}), kind="global",
                      modes=(Variant("grey_winter", snow=True, snow_colour=GREY_SNOW,
                                     recolour={"sky": GREY_WINTER_SKY}),))
PARTY_HAT_EDIT = EditDef(
    "party_hat", "Give the bear a party hat", "a statue of a bear on a stone pedestal",
    "a statue of a bear wearing a party hat on a stone pedestal",
    Variant("party_hat", add=(SceneObject("party_hat", _PARTY_HAT_SHAPE, PARTY_HAT),)),
    kind="geometry", modes=(Variant("gold_hat", add=(SceneObject("party_hat", _PARTY_HAT_SHAPE, PARTY_HAT_GOLD),)),))


def bear_world(config: SceneConfig, seed: int) -> World:
    hx, _, hz = BEAR_HEAD
    objects = [
        SceneObject("pedestal", Cylinder(centre=(0.0, 0.0, 0.0), radius=0.95, height=PEDESTAL_TOP), STONE),
        SceneObject("body", Ellipsoid(centre=(0.0, 0.0, 0.78), radii=(0.58, 0.32, 0.30)), FUR),
        SceneObject("head", Ellipsoid(centre=BEAR_HEAD, radii=(0.22, 0.20, 0.20)), FUR),
        SceneObject("snout", Ellipsoid(centre=(hx + 0.2, 0.0, hz - 0.05), radii=(0.11, 0.09, 0.08)), PAWS),
        SceneObject("tail", Ellipsoid(centre=(-0.58, 0.0, 0.86), radii=(0.07, 0.07, 0.07)), FUR),
    ]
    for side, y in (("left", 0.14), ("right", -0.14)):
        objects.append(SceneObject(f"ear_{side}", Ellipsoid(centre=(hx - 0.04, y, hz + 0.17),
                                                            radii=(0.05, 0.07, 0.07)), PAWS))
    for i, (x, y) in enumerate(((0.35, 0.17), (0.35, -0.17), (-0.35, 0.17), (-0.35, -0.17))):
        objects.append(SceneObject(f"leg_{i}", Cylinder(centre=(x, y, PEDESTAL_TOP), radius=0.1,
                                                        height=0.42), PAWS))
    # Rocks and shrubs around the pedestal (inside the camera circle) give SfM near points all round.
    for i, a in enumerate(np.linspace(0.3, 2 * np.pi + 0.3, 6, endpoint=False)):
        r = 1.7 + 0.25 * np.sin(3 * a)
        objects.append(SceneObject(f"rock_{i}", Ellipsoid(centre=(r * np.cos(a), r * np.sin(a), 0.05),
                                                          radii=(0.22, 0.18, 0.16)), ROCK))
    for i, a in enumerate(np.linspace(0.0, 2 * np.pi, 5, endpoint=False)):
        objects.append(SceneObject(f"shrub_{i}", Ellipsoid(centre=(6.5 * np.cos(a), 6.5 * np.sin(a), 0.4),
                                                           radii=(0.7, 0.7, 0.6)), FOLIAGE))
    objects += [SceneObject("ground", Disk(radius=config.dome_radius), GRAVEL),
                SceneObject("sky", Dome(radius=config.dome_radius), SKY)]
    return World(tuple(objects), seed=seed)


# --- portrait: a forward-facing head-and-shoulders capture before a hedge ---
SKIN = Material("skin", ((0.86, 0.66, 0.54), (0.80, 0.58, 0.47), (0.74, 0.50, 0.42)),
                frequency=4.0, octaves=5, patch_amount=0.25, detail=0.25, speckle=0.2)
HAIR = Material("hair", ((0.22, 0.14, 0.08), (0.30, 0.19, 0.10), (0.14, 0.09, 0.05)),
                frequency=5.0, octaves=6, patch_amount=0.3, detail=0.5)
SWEATER = Material("sweater", ((0.18, 0.32, 0.62), (0.14, 0.25, 0.52), (0.30, 0.45, 0.72)),
                   frequency=4.0, octaves=6, patch_amount=0.2, detail=0.4)
EYES = Material("eyes", ((0.10, 0.08, 0.07), (0.18, 0.13, 0.10), (0.85, 0.85, 0.82)),
                frequency=8.0, octaves=3, patch_amount=0.1, detail=0.2)
HEDGE = Material("hedge", ((0.16, 0.38, 0.14), (0.26, 0.48, 0.18), (0.55, 0.50, 0.30)),
                 frequency=1.6, octaves=7, patch_amount=0.4, detail=0.55)
PAVING = Material("paving", ((0.60, 0.57, 0.52), (0.48, 0.46, 0.43), (0.70, 0.62, 0.50)),
                  pattern="planks", plank_axis=(0.0, 1.0, 0.0), plank_width=0.3, frequency=1.0, octaves=6,
                  patch_amount=0.3, detail=0.4)
FELT = Material("felt", ((0.45, 0.30, 0.16), (0.36, 0.23, 0.12), (0.55, 0.40, 0.24)),
                frequency=5.0, octaves=5, patch_amount=0.2, detail=0.35)
RED_SWEATER = ((0.75, 0.12, 0.12), (0.60, 0.08, 0.09), (0.85, 0.30, 0.25))
SUNSET_SKY = ((0.30, 0.22, 0.16), (0.95, 0.55, 0.30), (0.98, 0.80, 0.55))
SUNSET_LIGHT = (1.18, 0.82, 0.58)

HEAD = (0.0, 0.0, 1.72)

CRIMSON_SWEATER = ((0.72, 0.10, 0.30), (0.58, 0.06, 0.22), (0.85, 0.28, 0.45))
PINK_SKY = ((0.30, 0.20, 0.22), (0.90, 0.55, 0.65), (0.98, 0.82, 0.85))
PINK_LIGHT = (1.12, 0.80, 0.90)
BLACK_FELT = Material("felt", ((0.10, 0.09, 0.08), (0.07, 0.06, 0.06), (0.18, 0.16, 0.14)),
                      frequency=5.0, octaves=5, patch_amount=0.2, detail=0.35)


def _cowboy_hat(felt: Material) -> tuple[SceneObject, ...]:
    return (SceneObject("hat_brim", Cylinder(centre=(HEAD[0], HEAD[1] + 0.01, HEAD[2] + 0.12), radius=0.32,
                                             height=0.03), felt),
            SceneObject("hat_crown", Cylinder(centre=(HEAD[0], HEAD[1] + 0.01, HEAD[2] + 0.14), radius=0.15,
                                              height=0.17), felt))


RED_SWEATER_EDIT = EditDef("red_sweater", "Turn his sweater red", "a man in a blue sweater in front of a hedge",
                           "a man in a red sweater in front of a hedge",
                           Variant("red_sweater", recolour={"sweater": RED_SWEATER}), kind="recolour",
                           modes=(Variant("crimson_sweater", recolour={"sweater": CRIMSON_SWEATER}),))
SUNSET_EDIT = EditDef("sunset", "Make it sunset", "a portrait of a man in front of a hedge at midday",
                      "a portrait of a man in front of a hedge in warm sunset light",
                      Variant("sunset", light=SUNSET_LIGHT, recolour={"sky": SUNSET_SKY}), kind="global",
                      modes=(Variant("pink_sunset", light=PINK_LIGHT, recolour={"sky": PINK_SKY}),))
COWBOY_HAT_EDIT = EditDef(
    "cowboy_hat", "Give him a cowboy hat", "a portrait of a man in front of a hedge",
    "a portrait of a man wearing a cowboy hat in front of a hedge",
    Variant("cowboy_hat", add=_cowboy_hat(FELT)), kind="geometry",
    modes=(Variant("black_hat", add=_cowboy_hat(BLACK_FELT)),))


def portrait_world(config: SceneConfig, seed: int) -> World:
    x, y, z = HEAD
    objects = [
        SceneObject("torso", Ellipsoid(centre=(0.0, 0.02, 0.98), radii=(0.52, 0.24, 0.46)), SWEATER),
        SceneObject("neck", Cylinder(centre=(0.0, 0.01, 1.38), radius=0.075, height=0.2), SKIN),
        SceneObject("head", Ellipsoid(centre=HEAD, radii=(0.15, 0.17, 0.21)), SKIN),
        SceneObject("hair", Ellipsoid(centre=(x, y + 0.035, z + 0.06), radii=(0.16, 0.165, 0.19)), HAIR),
        SceneObject("nose", Ellipsoid(centre=(x, y - 0.165, z - 0.02), radii=(0.028, 0.04, 0.05)), SKIN),
        SceneObject("ear_left", Ellipsoid(centre=(x - 0.15, y, z), radii=(0.025, 0.04, 0.06)), SKIN),
        SceneObject("ear_right", Ellipsoid(centre=(x + 0.15, y, z), radii=(0.025, 0.04, 0.06)), SKIN),
        SceneObject("eye_left", Ellipsoid(centre=(x - 0.06, y - 0.145, z + 0.04), radii=(0.025, 0.02, 0.016)),
                    EYES),
        SceneObject("eye_right", Ellipsoid(centre=(x + 0.06, y - 0.145, z + 0.04), radii=(0.025, 0.02, 0.016)),
                    EYES),
        # The backdrop: a tall hedge behind the figure, wider than the camera arc sees.
        SceneObject("hedge", box((0.0, 1.9, 2.0), (9.0, 0.4, 2.0)), HEDGE),
        SceneObject("ground", Disk(radius=config.dome_radius), PAVING),
        SceneObject("sky", Dome(radius=config.dome_radius), SKY),
    ]
    return World(tuple(objects), seed=seed)


TINY = SceneConfig("tiny", width=160, height=120, n_views=26, arc_degrees=200.0, camera_radius=5.0,
                   camera_height=2.2, height_wobble=0.25, fov_degrees=60.0, supersample=2, dome_radius=9.0)
CAMPSITE = SceneConfig("campsite", width=256, height=192, n_views=48, arc_degrees=360.0, camera_radius=6.5,
                       camera_height=2.6, height_wobble=0.3, fov_degrees=60.0, supersample=2,
                       dome_radius=11.0)
BEAR = SceneConfig("bear", width=256, height=192, n_views=48, arc_degrees=360.0, camera_radius=3.4,
                   camera_height=1.5, height_wobble=0.25, fov_degrees=60.0, supersample=2, dome_radius=9.0,
                   target_height=0.7)
PORTRAIT = SceneConfig("portrait", width=256, height=192, n_views=45, arc_degrees=80.0, camera_radius=2.3,
                       camera_height=1.65, height_wobble=0.12, fov_degrees=50.0, supersample=2,
                       dome_radius=12.0, target_height=1.45)

BUILDERS = {"tiny": (tiny_world, (SNOW_EDIT, BLUE_TENT_EDIT)),
            "campsite": (campsite_world, (SNOW_EDIT, BLUE_TENT_EDIT, AUTUMN_EDIT, CANOE_EDIT)),
            "bear": (bear_world, (PANDA_EDIT, WINTER_EDIT, PARTY_HAT_EDIT)),
            "portrait": (portrait_world, (RED_SWEATER_EDIT, SUNSET_EDIT, COWBOY_HAT_EDIT))}
SCENES: dict[str, SceneConfig] = {"tiny": TINY, "campsite": CAMPSITE, "bear": BEAR, "portrait": PORTRAIT}
