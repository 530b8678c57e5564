"""Grid cells -> steps. The shape of each row's DAG comes from what the stages declare they read.

Each stage names its inputs (`Stage.upstream`, e.g. evaluate reads "dataset", "fit", "edit", "original",
"perframe"); `PRODUCERS` says which stage's result each name is. A cell is wired from its own evaluate
step (node ROW) up: every declared input becomes the step of its producer, recursively, except for the
optional inputs that the cell's method or scene leaves out (`_reads`):

    scene -> preprocess -> fit -> edit[method, seed, params] -> evaluate[...]        (IDU methods)
                             |              perframe[seed] (<- gtviews) -> evaluate[per-frame, ...]
                             \\-> evaluate[original]  (the "original" input of edited rows)

With `methods = []` a cell is its unedited row alone: the reconstruction (SfM, f_S, its evaluation).

Identical invocations share one Step (and one key in the store), so preprocess and the static fit run
once per scene and fit setting. Labels name the scene edit (in multi-scene grids), the method, the seed
and the axis values the row reads; they are what run records and logs show.
"""
from __future__ import annotations

from pathlib import Path

from experiments.methods import ORIGINAL, Method
from experiments.workflow import grid
from experiments.workflow.cells import Cell, Workflow, WorkflowError
from experiments.workflow.scenes import DEFAULT_SCENES_DIR, Scene, captions, load_scene, scene_names
from pipeline.dag import Step
from pipeline.grid import GridError
from pipeline.paths import check_plain_name, confined

# The stage whose result each input name (as stages declare it in `upstream`) is. "original" is the
# evaluation of the unedited scene: edited rows reuse its renders and the per-frame baseline edits them.
PRODUCERS = {"scene": "scene", "dataset": "preprocess", "fit": "fit", "edit": "edit", "perframe": "perframe",
             "gtviews": "gtviews", "original": "evaluate"}
ROW = "row"                      # a cell's own evaluate step (an edited row's; the unedited row is "original")


def _stage_of(node: str) -> str:
    return "evaluate" if node == ROW else PRODUCERS[node]


class _Row:
    """One grid point: which inputs each of its steps reads, their parameters (recording the axes each
    step reads), then its steps, wired and labelled."""

    def __init__(self, point, scene: Scene, method: Method, texts: dict, fixed: dict, param_axes: list,
                 single: bool):
        self.point, self.scene, self.method, self.texts = point, scene, method, texts
        self.fixed, self.param_axes, self.single = fixed, param_axes, single
        self.edit_id, self.seed = point["edit"], point["seed"]
        self.order = {a.name: i for i, a in enumerate(param_axes)}
        self.inputs: dict[str, list[str]] = {}        # node -> the input nodes its step reads
        self.params: dict[str, dict] = {}             # node -> the step's parameters
        self.read: dict[str, dict] = {}               # node -> {axis name: value} its parameters came from
        self._visit("original" if method.is_original else ROW)

    # ---- shape -----------------------------------------------------------------------------------
    def _reads(self, node: str) -> list[str]:
        """The inputs the step of `node` reads: its stage's declared upstream names, less the optional
        ones this row does not use."""
        from pipeline.registry import load_stage
        from stages import STAGES

        declared = load_stage(STAGES, _stage_of(node)).upstream
        if node == ROW:       # an edited row evaluates the edit (IDU) or the per-frame images, beside the original
            unused = {"perframe"} if self.method.flags is not None else {"edit"}
        elif node == "original":                    # the unedited scene: f_S alone
            unused = {"edit", "perframe", "original"}
        elif node == "dataset":                     # a user folder is an external input, not a scene step
            unused = set() if self.scene.procedural else {"scene"}
        elif node == "perframe":                    # only the InstructPix2Pix emulator needs the ground truth
            unused = set() if self._params_of(node).get("editor", "synthetic") == "synthetic" else {"gtviews"}
        else:
            unused = set()
        return [name for name in declared if name not in unused]

    def _visit(self, node: str) -> None:
        if node in self.inputs:
            return
        self._params_of(node)
        self.inputs[node] = self._reads(node)
        for name in self.inputs[node]:
            self._visit(name)

    def _closure(self, node: str) -> set[str]:
        found, todo = set(), [node]
        while todo:
            current = todo.pop()
            if current not in found:
                found.add(current)
                todo += self.inputs[current]
        return found

    # ---- parameters ------------------------------------------------------------------------------
    def _axis_params(self, node: str, stage: str, only: tuple = ()) -> dict:
        """The parameters of `stage` at this grid point (restricted to `only`); records in self.read[node]
        which parameter axes they came from."""
        values = {k: v for k, v in self.fixed[stage].items() if not only or k in only}
        read = self.read.setdefault(node, {})
        for axis in self.param_axes:
            for st, param in axis.targets:
                if st == stage and (not only or param in only):
                    values[param] = self.point[axis.name]
                    read[axis.name] = self.point[axis.name]
        return values

    def _params_of(self, node: str) -> dict:
        if node not in self.params:
            self.params[node] = self._compute_params(node)
        return self.params[node]

    def _compute_params(self, node: str) -> dict:
        texts, edit_id, seed = self.texts, self.edit_id, self.seed
        if node == "scene":
            return {"name": self.scene.name, **self._axis_params(node, "scene")}
        if node in ("dataset", "fit"):
            return self._axis_params(node, _stage_of(node))
        if node in (ROW, "original"):
            return {"edit_id": edit_id, "source_caption": texts["source_caption"],
                    "target_caption": texts["target_caption"], **self._axis_params(node, "evaluate")}
        if node == "edit":
            return {**self._axis_params(node, "edit"), **self.method.edit_params(),
                    "instruction": texts["instruction"], "edit_id": edit_id, "seed": seed}
        if node == "perframe":
            return {**self._axis_params(node, "perframe"),
                    **self._axis_params(node, "edit", grid.PERFRAME_FROM_EDIT),
                    "instruction": texts["instruction"], "edit_id": edit_id, "seed": seed}
        if node == "gtviews":
            # The procedural scene re-rendered exactly: with the scene step's supersample.
            scene_params = self._params_of("scene") if self.scene.procedural else {}
            return {"edit_id": edit_id, "scene_supersample": int(scene_params.get("supersample", 0))}
        raise AssertionError(f"no parameters for input '{node}'")

    def axes_read(self, node: str) -> tuple:
        """The (axis, value) pairs read by the step of `node` and everything upstream of it, in axis order."""
        read = {k: v for n in self._closure(node) for k, v in self.read.get(n, {}).items()}
        return tuple(sorted(read.items(), key=lambda kv: self.order[kv[0]]))

    # ---- steps -----------------------------------------------------------------------------------
    def _label(self, node: str) -> str:
        scene = self.scene.name
        prefix = "" if self.single else f"{scene}/{self.edit_id}"
        if node == "original":
            parts = [scene, "original"] if self.single else ["original"]
            return f"evaluate[{grid.label_of(prefix, parts, dict(self.axes_read(node)))}]"
        if node in (ROW, "edit", "perframe"):       # the row's own steps: named by its method and seed
            row = grid.label_of(prefix, [self.method.label, f"seed {self.seed}"], dict(self.axes_read(ROW)))
            return f"{_stage_of(node)}[{row}]"
        return f"{_stage_of(node)}[{scene}/{self.edit_id}]" if node == "gtviews" else f"{_stage_of(node)}[{scene}]"

    def steps(self, builder: grid.GridBuilder) -> dict[str, Step]:
        made: dict[str, Step] = {}

        def make(node: str) -> Step:
            if node not in made:
                inputs = {name: make(name) for name in self.inputs[node]}
                if node == "dataset" and not self.scene.procedural:
                    inputs.update(self.scene.inputs)            # {"source": External(user folder)}
                made[node] = builder.make(_stage_of(node), self.params[node], inputs, label=self._label(node))
            return made[node]

        make("original" if self.method.is_original else ROW)
        return made


def expand(path: Path, settings: dict, stage_params: dict, axes_doc: dict) -> Workflow:
    names = scene_names(path, settings)
    scenes_dir = Path(settings.get("scenes_dir", DEFAULT_SCENES_DIR))
    scenes = {name: load_scene(path, settings, name, scenes_dir) for name in names}
    methods = {m.label: m for m in grid.parse_methods(WorkflowError, path, settings)}
    reconstruct_only = not methods          # methods = []: the unedited rows alone
    if reconstruct_only:
        methods = {ORIGINAL.label: ORIGINAL}
    seeds = grid.parse_seeds(WorkflowError, path, settings.get("seeds", [0]))
    param_axes, fixed = grid.param_axes(WorkflowError, path, stage_params, axes_doc)
    axes = grid.grid_axes(names, lambda scene: scenes[scene].edit_ids, list(methods.values()), seeds, param_axes)
    try:
        grid_cells = grid.expand(axes, _filters(path, settings, "include"), _filters(path, settings, "exclude"),
                                 where=str(path))
    except GridError as err:
        raise WorkflowError(str(err)) from None
    builder = grid.GridBuilder()
    # One scene edit in the whole grid: the step labels of the single-scene workflows (run records
    # and logs keep reading "edit[DF+SA, seed 0]"); otherwise every label names its scene edit.
    single = len({(p["scene"], p["edit"]) for p in grid_cells}) == 1
    cells: list[Cell] = []
    listed: set[int] = set()
    read_anywhere: set[str] = set()
    with_original = bool(settings.get("original", True))
    texts: dict[tuple[str, str], dict] = {}

    for point in grid_cells:
        scene = scenes[point["scene"]]
        key = (scene.name, point["edit"])
        if key not in texts:
            texts[key] = captions(path, settings, scene, point["edit"], required=not reconstruct_only)
        row = _Row(point, scene, methods[point["method"]], texts[key], fixed, param_axes, single)
        steps = row.steps(builder)
        original = steps["original"]
        if with_original and id(original) not in listed:
            listed.add(id(original))
            cells.append(Cell(ORIGINAL, original, scene=scene.name, edit_id=point["edit"],
                              params=row.axes_read("original")))
        if reconstruct_only:
            read_anywhere |= {name for name, _ in row.axes_read("original")}
            continue
        evaluate = steps[ROW]
        read_anywhere |= {name for name, _ in row.axes_read(ROW)}
        if id(evaluate) not in listed:          # a per-frame row does not multiply over edit-only axes
            listed.add(id(evaluate))
            cells.append(Cell(row.method, evaluate, point["seed"], steps.get("edit"), scene.name, point["edit"],
                              row.axes_read(ROW), steps.get("perframe")))

    unread = [a for a in param_axes if a.name not in read_anywhere]
    if unread:
        axis = unread[0]
        raise WorkflowError(f"{path}: axis '{axis.name}' (sets {', '.join(f'{s}.{p}' for s, p in axis.targets)}) "
                            f"is read by no cell of the grid: methods {', '.join(methods)} never run that "
                            f"stage. Remove the axis or add a method that uses it.")
    first = cells[0]
    names = list(dict.fromkeys(c.scene for c in cells))        # the scenes left after the filters
    sizes = [("scene", len(names)), ("edit", len({(c.scene, c.edit_id) for c in cells})),
             ("method", len({c.label for c in cells if not c.is_original})), ("seed", len(seeds))]
    name = check_plain_name(settings["name"], f"{path}: [workflow] name") if "name" in settings else path.stem
    return Workflow(name=name, path=path,
                    scene_name=names[0] if len(names) == 1 else f"{len(names)}-scenes",
                    scene_origin=scenes[first.scene].origin, edit_id=first.edit_id, steps=builder.steps,
                    cells=cells, report_dir=_report_dir(path, settings, names), settings=settings, scenes=names,
                    axes=sizes + [(a.name, len(a.values)) for a in param_axes],
                    **texts[(first.scene, first.edit_id)])


def _filters(path: Path, settings: dict, key: str) -> list:
    raw = settings.get(key, [])
    raw = [raw] if isinstance(raw, dict) else raw
    if not isinstance(raw, list) or not all(isinstance(f, dict) for f in raw):
        raise WorkflowError(f"{path}: [workflow] {key} must be a list of tables, e.g. "
                            f"{key} = [{{scene = \"tiny\", method = \"IN2N\"}}], got {raw!r}.")
    return raw


def _report_dir(path: Path, settings: dict, scenes: list[str]) -> Path:
    name = str(settings.get("name", path.stem))
    raw = str(settings.get("report_dir", "reports/{scene}" if len(scenes) == 1 else f"reports/{name}"))
    if "{scene}" in raw and len(scenes) > 1:
        raise WorkflowError(f"{path}: report_dir '{raw}' uses {{scene}} but the grid has {len(scenes)} scenes "
                            f"({', '.join(scenes)}); set report_dir without {{scene}} (e.g. reports/{name}).")
    # The scene name cannot lead the report elsewhere: it stays inside the folder before the placeholder.
    return confined(raw.replace("{scene}", scenes[0]), Path(raw.split("{")[0] + "x").parent,
                    f"{path}: [workflow] report_dir")

