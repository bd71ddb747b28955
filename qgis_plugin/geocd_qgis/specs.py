"""The table of geocd Processing algorithms: one entry per ``geocd`` CLI call.

This module is plain Python (no ``qgis`` import) so that geocd's own test suite
can check the table against the CLI (every option named here must exist in the
click command, with the same default). :mod:`.algorithm` turns each
:class:`AlgSpec` into a ``QgsProcessingAlgorithm``.

Adding an algorithm when a new ``geocd`` command lands is one :class:`AlgSpec`
entry in :data:`ALGORITHMS`: the command, its parameters (QGIS parameter name →
CLI option) and the outputs named in the command's ``result`` line.

Parameter kinds
---------------
``raster``            raster layer (file based) → its path
``rasters``           several raster layers → the option repeated per layer (or positionals)
``vector``            vector features (any layer; "selected features only" honoured) → a file path
``file``              a file (``extension``/``file_filter`` filter the dialog) → its path
``folder``            an existing folder → its path
``number`` / ``int``  a float / an integer (``unit`` is shown in the label)
``numbers``           comma-separated floats → the option repeated per value
``enum``              one of ``options`` ((label, CLI value), ...)
``bool``              flag: ``cli`` is passed when true
``string``            free text; ``multiple=True``: comma-separated → the option repeated
``crs``               a CRS → its authid (e.g. ``EPSG:32610``) or WKT
``range``             two numbers (min, max) → ``--opt MIN MAX``
``pair``              two numbers typed "a, b" (e.g. sun azimuth, elevation) → ``--opt A B``
``extent``            a map extent → (xmin, ymin, xmax, ymax, crs) (manifest AOI only)
``folder_destination`` / ``file_destination``   where geocd writes

``cli=None`` marks a positional argument (in table order). A parameter with a
``manifest`` role is not passed on the command line: it goes into a scene
manifest the plugin writes (see :func:`build_manifest`), which is then the
command's positional argument; this is how image layers picked in QGIS become a
geocd scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

#: titles of GeoPackage layers in the layer tree
LAYER_TITLES = {
    "changes": "Changed regions",
    "buildings": "Buildings by change class",
    "curves": "Significance curves",
    "rectangles": "Building rectangles (marked point process)",
}

#: the output folder parameter (``--out``) of every algorithm that writes a folder of products
OUTPUT_FOLDER = "OUTPUT"


@dataclass(frozen=True)
class Param:
    name: str
    kind: str
    label: str
    cli: Optional[str] = None
    default: Any = None
    optional: bool = False
    advanced: bool = False
    help: str = ""
    unit: str = ""
    options: tuple = ()  # enum: ((label, cli value), ...)
    min: Optional[float] = None
    max: Optional[float] = None
    extension: str = ""  # file: e.g. "yaml"
    file_filter: str = ""  # file / file_destination: Qt filter, e.g. "Scene manifests (*.yaml *.yml *.json)"
    geometry: str = "any"  # vector: polygon|point|line|any
    multiple: bool = False  # string: comma-separated values → repeated option
    #: the default is also the CLI's own default: the option is not passed when the value equals it
    #: (keeps command lines short and lets CLI-side precedence rules, e.g. `synth --params`, work)
    cli_default: bool = True
    #: role in a manifest the plugin writes: images_a, images_b, dem, dem_datum, footprints, aoi, aoi_vector,
    #: posting, scene_class (not passed on the command line)
    manifest: Optional[str] = None


@dataclass(frozen=True)
class Output:
    """One product announced in geocd's ``result`` line (``outputs[key]``).

    kind: ``raster`` | ``vector`` (a GeoPackage; ``layers`` names the layers to load, those present are) |
    ``file`` | ``folder``. ``style``: applied when the product carries no style of its own (rasters: a
    ``<name>.qml`` sidecar; GeoPackages: the ``layer_styles`` table): a QML file in ``geocd_qgis/styles``, or
    ``auto:probability`` (0–1 ramp) / ``auto:height`` (colour ramp over the layer's range).
    """

    key: str
    name: str
    kind: str
    label: str
    layers: tuple = ()
    style: Optional[str] = None
    load: bool = True


@dataclass(frozen=True)
class AlgSpec:
    name: str
    display: str
    group: str
    group_id: str
    command: tuple
    short_help: str
    params: tuple
    outputs: tuple = ()
    #: load every raster/GeoPackage of the result that no :class:`Output` names (e.g. one pair-DEM per pair)
    load_unlisted: bool = False
    #: result keys with this prefix are not loaded by ``load_unlisted``
    skip_prefixes: tuple = ()
    #: name of a string output that receives the command's stdout
    stdout_output: Optional[str] = None
    tags: tuple = ()
    #: extra CLI tokens always passed after the command
    fixed_args: tuple = ()
    #: the plugin writes a scene manifest from the ``manifest`` parameters and passes it as the positional argument
    writes_manifest: bool = False
    #: the geocd command is not in the CLI yet: the entry is kept out of the provider
    pending: bool = False


def _out_folder(help_: str = "Folder for geocd's products (created if missing).") -> Param:
    return Param(OUTPUT_FOLDER, "folder_destination", "Output folder", cli="--out", help=help_)


_MANIFEST = Param(
    "MANIFEST",
    "file",
    "Scene manifest",
    extension="yaml",
    file_filter="Scene manifests (*.yaml *.yml *.json);;All files (*)",
    help="scene.yaml listing the epochs, images and cameras (see geocd's README).",
)
_CONFIDENCES = Param(
    "CONFIDENCES",
    "numbers",
    "Confidence levels (comma-separated)",
    cli="--confidence",
    unit="%",
    optional=True,
    advanced=True,
    help="Default 90, 95, 99.",
)
_SCHEDULER = Param(
    "SCHEDULER",
    "string",
    "Tiled runs: scheduler (sync, threads, processes, or a Dask address)",
    cli="--scheduler",
    optional=True,
    advanced=True,
    help="Default: a local Dask cluster with one worker per core; tcp://host:8786 for a running "
    "dask.distributed scheduler.",
)
_POSTING = Param(
    "POSTING",
    "number",
    "Grid posting",
    cli="--posting",
    unit="m",
    optional=True,
    min=0.0,
    help="Default: the manifest's AOI posting, else the images' GSD.",
)
_DATUMS = (
    ("from the file's CRS", ""),
    ("ellipsoid", "ellipsoid"),
    ("EGM96 geoid", "egm96"),
    ("EGM2008 geoid", "egm2008"),
)
#: the two DEMs of demdiff, given in turn to its repeated --vertical-datum ("file": what the file says)
_DATUMS_AB = (("from the file's CRS", "file"), *_DATUMS[1:])

#: products of a change test (geocd.change.products.write_change_products)
_CHANGE_OUTPUTS = (
    Output("change", "CHANGE", "raster", "Change: dz, dtilde, score, confidence"),
    Output("change_mask", "CHANGE_MASK", "raster", "Change mask (raised / lowered / unchanged)"),
    Output("changes", "CHANGES", "vector", "Changed regions", layers=("changes", "buildings")),
    Output("quicklook", "QUICKLOOK", "file", "Quick-look map (PNG)", load=False),
    Output("scatter", "SCATTER", "file", "Score × |Δ| scatter with significance curves (PNG)", load=False),
)

GROUP_INSPECT = ("Inspect", "inspect")
GROUP_DEM = ("DEMs and stereo", "dems")
GROUP_CHANGE = ("3-D change", "change")
GROUP_VOLUME = ("Volumetric model", "volume")
GROUP_DATA = ("Data", "data")
GROUP_LANDCOVER = ("Land cover", "landcover")

#: where the land-cover algorithms place the ground grid and what rays meet (geocd landcover --manifest/--dem/...)
_LANDCOVER_SCENE = (
    Param(
        "MANIFEST",
        "file",
        "Scene manifest (AOI grid, DEM, footprints)",
        cli="--manifest",
        optional=True,
        file_filter="Scene manifests (*.yaml *.yml *.json);;All files (*)",
    ),
    Param("DEM", "raster", "Terrain DEM (its grid is the default AOI grid)", cli="--dem", optional=True),
    Param(
        "DEM_DATUM",
        "enum",
        "Vertical datum of the DEM (when its file does not say)",
        cli="--vertical-datum",
        options=_DATUMS,
        default=0,
        optional=True,
        advanced=True,
    ),
    Param(
        "FOOTPRINTS",
        "vector",
        "Building footprints (occupancy; extruded by height to stop rays)",
        cli="--footprints",
        optional=True,
        geometry="polygon",
    ),
    Param(
        "HEIGHT_FIELD",
        "string",
        "Footprint attribute with the building height above ground (m)",
        cli="--height-field",
        optional=True,
        advanced=True,
        help="Default: height_m, height, ...",
    ),
    Param(
        "DSM",
        "raster",
        "DSM (e.g. from geocd stereo): the surface rays meet",
        cli="--dsm",
        optional=True,
        advanced=True,
    ),
    Param(
        "POSTING",
        "number",
        "Grid posting",
        cli="--posting",
        unit="m",
        optional=True,
        min=0.0,
        help="Default: the manifest's AOI posting, else the DEM's.",
    ),
)


#: the 2-D screen's options (geocd screen), shared by its two algorithms
_SCREEN_PARAMS = (
    Param(
        "FEATURE",
        "enum",
        "Grid feature",
        cli="--feature",
        default=0,
        options=(
            ("grey local patch", "patch"),
            ("dense DAISY (multi-scale)", "daisy"),
            ("seeded random-filter bank", "randbank"),
            ("CNN pooling layer (weights file)", "cnn"),
        ),
    ),
    Param(
        "CELL",
        "int",
        "Grid cell",
        cli="--cell",
        unit="px",
        default=16,
        min=2,
        max=512,
        help="Patch, DAISY and random bank; a CNN layer's stride sets its own.",
    ),
    Param(
        "BACKBONE",
        "string",
        "CNN backbone (vgg19, resnet18, efficientnet_lite0, ...)",
        cli="--backbone",
        optional=True,
        advanced=True,
    ),
    Param(
        "WEIGHTS",
        "file",
        "CNN weights (.npz or .pt state_dict)",
        cli="--weights",
        optional=True,
        advanced=True,
        file_filter="Weights (*.npz *.pt *.pth);;All files (*)",
    ),
    Param(
        "LAYER",
        "string",
        "CNN layer (pool1..pool5, layer1..layer4, stage1..stage7)",
        cli="--layer",
        optional=True,
        advanced=True,
    ),
    Param(
        "SUPERPIXELS",
        "enum",
        "Superpixels",
        cli="--superpixels",
        default=0,
        advanced=True,
        options=(("Felzenszwalb (thesis)", "felzenszwalb"), ("SLIC", "slic"), ("none", "none")),
    ),
    Param(
        "VEGETATION",
        "enum",
        "Set aside vegetation",
        cli="--vegetation",
        default=0,
        advanced=True,
        options=(("seen in both dates", "both"), ("seen in either date", "either"), ("off", "off")),
    ),
    Param(
        "SHADOW",
        "enum",
        "Set aside cast shadows",
        cli="--shadow",
        default=0,
        advanced=True,
        options=(("seen in both dates", "both"), ("seen in either date", "either"), ("off", "off")),
    ),
    Param(
        "CONFIDENCE",
        "number",
        "Confidence (percentile of the no-change pair)",
        cli="--confidence",
        unit="%",
        default=99.0,
        min=50.0,
        max=99.99,
    ),
    Param(
        "THRESHOLD",
        "number",
        "Fixed dissimilarity threshold (instead of the confidence)",
        cli="--threshold",
        optional=True,
        min=0.0,
        max=2.0,
        advanced=True,
    ),
)

ALGORITHMS: tuple[AlgSpec, ...] = (
    AlgSpec(
        name="info",
        display="Describe a geocd input",
        group=GROUP_INSPECT[0],
        group_id=GROUP_INSPECT[1],
        command=("info",),
        short_help="Shows what geocd sees in an image, camera file, DEM, vector file or scene manifest: camera kind "
        "(RPC or frame), ground footprint, CRS, vertical datum, data type and the RPC height range. "
        "Use it to check that geocd reads your inputs before a long run.",
        params=(
            Param(
                "INPUT",
                "file",
                "Input (image, camera file, DEM, vector or scene manifest)",
                help="Any file geocd reads: GeoTIFF/NITF with RPC tags or a camera sidecar, a vendor RPC file, "
                "a DEM, a vector file or a scene manifest (scene.yaml).",
            ),
        ),
        stdout_output="INFO",
        tags=("metadata", "rpc", "camera"),
    ),
    AlgSpec(
        name="stereo",
        display="Stereo pair-DEMs (scene manifest)",
        group=GROUP_DEM[0],
        group_id=GROUP_DEM[1],
        command=("stereo",),
        short_help="Matches every image pair of the chosen epochs of a scene manifest in object space (RPC and frame "
        "cameras alike) and writes one pair-DEM per pair: a Cloud-Optimized GeoTIFF with bands z "
        "(ellipsoidal height, m), score, g (px of disparity per m), valid, ncc, ssd and flags. "
        "Every pair-DEM is loaded when the run ends (output 'All loaded layers' feeds the "
        "self-consistency model in a graphical model).",
        params=(
            _MANIFEST,
            Param(
                "EPOCHS",
                "string",
                "Epochs (comma-separated; empty = every epoch with 2+ images)",
                cli="--epoch",
                optional=True,
                multiple=True,
            ),
            _out_folder("Pair-DEMs go to OUTPUT/stereo/EPOCH/A__B.tif."),
            _POSTING,
            Param(
                "WINDOW",
                "int",
                "Matching window side (odd)",
                cli="--window",
                unit="cells",
                optional=True,
                min=3,
                max=63,
                advanced=True,
                help="Default 7.",
            ),
            Param(
                "HEIGHT_RANGE",
                "range",
                "Height search range (ellipsoidal)",
                cli="--height-range",
                unit="m",
                optional=True,
                advanced=True,
                help="Default: prior DEM ± margin, else the cameras' RPC height range.",
            ),
            Param(
                "DEM_MARGIN",
                "number",
                "Search margin around the prior DEM",
                cli="--dem-margin",
                unit="m",
                optional=True,
                min=0.0,
                advanced=True,
                help="Default 30 m.",
            ),
            Param(
                "SCORE",
                "enum",
                "Score band",
                cli="--score",
                optional=True,
                advanced=True,
                options=(("MDL (bits/pixel, default)", "mdl"), ("NCC", "ncc"), ("SSD", "ssd")),
            ),
            Param(
                "SCORE_SUBWINDOW",
                "int",
                "MDL score: sub-window side (odd)",
                cli="--score-subwindow",
                unit="cells",
                optional=True,
                min=3,
                max=63,
                advanced=True,
                help="The MDL score of a match is the worst of these sub-windows of its matching window. "
                "Default 3; a value ≥ the window scores the whole window.",
            ),
            Param(
                "SURFACE_MEDIAN",
                "int",
                "Median of the valid heights (odd side; 1 = off)",
                cli="--surface-median",
                unit="cells",
                optional=True,
                min=1,
                max=63,
                advanced=True,
                help="Default: the matching window.",
            ),
            Param(
                "ISOLATION_MIN_CELLS",
                "int",
                "Smallest valid surface patch (1 = off)",
                cli="--isolation-min-cells",
                unit="cells",
                optional=True,
                min=1,
                max=10000,
                advanced=True,
                help="A valid height whose patch of neighbours within one pixel of disparity holds fewer cells "
                "is invalid (flag not_unique). Default: one matching window (window² cells).",
            ),
            Param(
                "NO_FILL",
                "bool",
                "Leave holes narrower than the matching window empty",
                cli="--no-fill",
                default=False,
                advanced=True,
                help="By default z holds interpolated heights there, flagged 'filled' and not valid.",
            ),
            Param(
                "TILE_SIZE",
                "int",
                "Tile side (memory bound)",
                cli="--tile-size",
                unit="cells",
                optional=True,
                min=32,
                advanced=True,
                help="Default 256 (the in-memory plane sweep's tile); for a tiled run the Dask tile, default 1024.",
            ),
            Param(
                "TILED",
                "bool",
                "Match tile by tile (whole scenes: bounded memory, resumable, on Dask)",
                cli="--tiled",
                default=False,
                advanced=True,
                help="Run the same algorithm again after a cancel or a crash: finished tiles are reused.",
            ),
            _SCHEDULER,
        ),
        load_unlisted=True,
        tags=("stereo", "dem", "rpc", "matching", "photogrammetry"),
    ),
    AlgSpec(
        name="stereopair",
        display="Stereo DEM from an image pair (layers)",
        group=GROUP_DEM[0],
        group_id=GROUP_DEM[1],
        command=("stereo",),
        writes_manifest=True,
        short_help="Matches two images of the same date (GeoTIFF/NITF with RPC tags or an RPC/frame camera sidecar) "
        "and writes their pair-DEM (bands z = ellipsoidal height in m, score, g, valid, ncc, ssd, flags). "
        "A prior DEM narrows the height search; the AOI limits the grid. The scene manifest written "
        "for geocd is kept in the output folder (scene_from_qgis.json) to rerun the same thing with "
        "the command line.",
        params=(
            Param("IMAGE_A", "raster", "Image 1", manifest="images_a"),
            Param("IMAGE_B", "raster", "Image 2", manifest="images_a"),
            Param("DEM", "raster", "Prior DEM (optional)", optional=True, manifest="dem"),
            Param(
                "DEM_DATUM",
                "enum",
                "Vertical datum of the prior DEM",
                options=_DATUMS,
                default=0,
                optional=True,
                manifest="dem_datum",
                advanced=True,
            ),
            Param("AOI", "extent", "Area of interest (default: the images' overlap)", optional=True, manifest="aoi"),
            Param(
                "POSTING",
                "number",
                "Grid posting",
                unit="m",
                optional=True,
                min=0.0,
                manifest="posting",
                help="Default: the images' GSD.",
            ),
            _out_folder("The pair-DEM goes to OUTPUT/stereo/A/<image1>__<image2>.tif."),
            Param(
                "WINDOW",
                "int",
                "Matching window side (odd)",
                cli="--window",
                unit="cells",
                optional=True,
                min=3,
                max=63,
                advanced=True,
                help="Default 7.",
            ),
            Param(
                "HEIGHT_RANGE",
                "range",
                "Height search range (ellipsoidal)",
                cli="--height-range",
                unit="m",
                optional=True,
                advanced=True,
            ),
        ),
        load_unlisted=True,
        tags=("stereo", "dem", "rpc", "pair"),
    ),
    AlgSpec(
        name="ortho",
        display="True orthoimages (scene manifest)",
        group=GROUP_DEM[0],
        group_id=GROUP_DEM[1],
        command=("ortho",),
        short_help="Orthorectifies every image of the chosen epochs of a scene manifest (RPC and frame cameras "
        "alike) onto the AOI grid with a surface model: a true ortho, where a cell hidden from the "
        "camera (behind a building) is nodata instead of the building's pixels. The DSM of each epoch "
        "is geocd stereo's unless one is given. Writes per image a Cloud-Optimized GeoTIFF in the "
        "image's own bands and data type (GDAL mask = not observed), a status raster (seen / occluded / "
        "outside / no height) and QGIS styles; every ortho is loaded when the run ends.",
        params=(
            _MANIFEST,
            Param(
                "EPOCHS", "string", "Epochs (comma-separated; empty = all)", cli="--epoch", optional=True, multiple=True
            ),
            Param(
                "IMAGES",
                "string",
                "Images (comma-separated names; empty = all)",
                cli="--image",
                optional=True,
                multiple=True,
            ),
            Param(
                "DSM",
                "raster",
                "Surface model for every epoch (default: geocd stereo per epoch)",
                cli="--dsm",
                optional=True,
            ),
            Param(
                "DSM_SOURCE",
                "enum",
                "Where each epoch's DSM comes from",
                cli="--dsm-source",
                default=0,
                advanced=True,
                options=(
                    ("the given DSM, else geocd stereo, else the manifest's DEM", "auto"),
                    ("geocd stereo", "stereo"),
                    ("the given DSM or the manifest's DEM", "dem"),
                ),
            ),
            _out_folder("Orthos go to OUTPUT/ortho/EPOCH/NAME.tif."),
            _POSTING,
            Param(
                "RESAMPLING",
                "enum",
                "Resampling",
                cli="--resampling",
                default=0,
                advanced=True,
                options=(("bilinear", "bilinear"), ("nearest (class labels)", "nearest")),
            ),
            Param(
                "NO_OCCLUSION",
                "bool",
                "Classic ortho (do not mask hidden cells)",
                cli="--no-occlusion",
                default=False,
                advanced=True,
            ),
            Param(
                "OCCLUSION_TOL",
                "number",
                "Occlusion tolerance",
                cli="--occlusion-tol",
                unit="m",
                optional=True,
                min=0.0,
                advanced=True,
                help="Default: max(0.5 m, 3 × the DSM's local noise).",
            ),
            Param(
                "VIEW_BANDS",
                "bool",
                "Also write the view geometry (zenith, azimuth, incidence)",
                cli="--view-bands",
                default=False,
                advanced=True,
            ),
        ),
        load_unlisted=True,
        tags=("ortho", "orthorectification", "true ortho", "rpc", "frame", "occlusion"),
    ),
    AlgSpec(
        name="mpp",
        display="Buildings and their changes, marked point process (scene manifest)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("mpp",),
        short_help="Finds the buildings of two dates and which are new, demolished or unchanged, with no footprint "
        "database: rectangles optimised by multiple birth and death (Benedek, Descombes & Zerubia), on "
        "true orthos of one view per epoch (geocd ortho) with geocd's height term from the stereo DSMs. "
        "Loads the buildings and rectangles layers (change class, confidence in %) and a class raster, "
        "styled. Same seed, same result.",
        params=(
            _MANIFEST,
            _out_folder("Layers go to OUTPUT/mpp/; orthos and DSMs to OUTPUT/ortho/."),
            Param(
                "METHOD",
                "enum",
                "Model",
                cli="--method",
                default=0,
                options=(
                    ("joint detection (ED, the paper's)", "ED"),
                    ("each date alone, then compared (SD)", "SD"),
                    ("edge-only verification (EV)", "EV"),
                ),
            ),
            Param(
                "HEIGHT",
                "enum",
                "Height term from the DSMs",
                cli="--height",
                default=0,
                options=(("when DSMs are available", "auto"), ("on", "on"), ("off (the paper's model)", "off")),
            ),
            Param(
                "STEP",
                "enum",
                "Height-step term (a building's outline steps down steeply)",
                cli="--step",
                default=2,
                options=(("on: required", "and"), ("in the height ring (dense blocks)", "ring"), ("off", "off")),
                advanced=True,
            ),
            Param(
                "EDGE_FIT",
                "enum",
                "Fit the rectangles' sides onto the walls after the annealing",
                cli="--edge-fit",
                default=0,
                options=(
                    ("image edges where the DSM has a wall", "joint"),
                    ("image edges alone", "image"),
                    ("off", "off"),
                ),
                advanced=True,
            ),
            Param(
                "EDGE_FIT_TURN",
                "enum",
                "Turn the rectangles onto their strongest edges after the side fit",
                cli="--edge-fit-turn",
                default=0,
                options=(("on", "on"), ("off", "off")),
                advanced=True,
            ),
            Param(
                "EDGE_FIT_GROW",
                "enum",
                "Grow the rectangles over the raised block they stand on, then onto its walls",
                cli="--edge-fit-grow",
                default=0,
                options=(("on", "on"), ("off", "off")),
                advanced=True,
            ),
            Param(
                "EDGE_FIT_CARVE",
                "enum",
                "Cut a corner notch (an L of two rectangles) where the image and DSM show one",
                cli="--edge-fit-carve",
                default=0,
                options=(("on", "on"), ("off", "off")),
                advanced=True,
            ),
            Param(
                "WALL_BLUR",
                "enum",
                "Height term: skip the DSM's blurred walls (measured on each image)",
                cli="--wall-blur",
                default=0,
                options=(("off", "off"), ("measured", "measured")),
                advanced=True,
            ),
            Param(
                "ABSENCE",
                "enum",
                "A new or demolished building needs ground there in the other date's DSM",
                cli="--absence",
                default=0,
                options=(("off", "off"), ("on", "height")),
                advanced=True,
            ),
            Param(
                "CHANGE_EVIDENCE",
                "enum",
                "What says a building changed (with the height term)",
                cli="--change-evidence",
                default=0,
                options=(
                    ("the DSMs: it stands on one date only", "height"),
                    ("the image texture (the paper's)", "texture"),
                    ("both (mean)", "both"),
                ),
                advanced=True,
            ),
            Param(
                "EPOCH_A", "string", "Earlier epoch (default: the first)", cli="--epoch-a", optional=True, advanced=True
            ),
            Param(
                "EPOCH_B", "string", "Later epoch (default: the last)", cli="--epoch-b", optional=True, advanced=True
            ),
            Param(
                "VIEW_A",
                "string",
                "Image of epoch A (default: the most vertical view)",
                cli="--image-a",
                optional=True,
                advanced=True,
            ),
            Param(
                "VIEW_B",
                "string",
                "Image of epoch B (default: the most vertical view)",
                cli="--image-b",
                optional=True,
                advanced=True,
            ),
            Param(
                "CHANGE_PRIOR",
                "raster",
                "3-D change evidence (e.g. sc_change.tif of a full run)",
                cli="--change-prior",
                optional=True,
                advanced=True,
            ),
            Param("SEED", "int", "Random seed", cli="--seed", default=0, min=0, advanced=True),
            _POSTING,
        ),
        outputs=(
            Output("buildings", "BUILDINGS", "vector", "Buildings and rectangles", layers=("buildings", "rectangles")),
            Output("classes", "CLASSES", "raster", "Building classes (unchanged / demolished / new)"),
            Output("quicklook", "QUICKLOOK", "file", "Quick-look (PNG)", load=False),
            Output("summary", "SUMMARY", "file", "Run summary (JSON)", load=False),
        ),
        tags=("buildings", "change detection", "marked point process", "object", "2d", "ortho"),
    ),
    AlgSpec(
        name="mppimages",
        display="Buildings and their changes, marked point process (two images)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("mpp",),
        short_help="The marked point process on two georeferenced images of different dates (e.g. orthos): the "
        "later one is resampled onto the earlier one's grid when they differ. With a DSM of each date "
        "the height term is used. Grey images: the colour and shadow terms are dropped (the log says so).",
        params=(
            Param("IMAGE_A", "raster", "Earlier image", cli="--image-a"),
            Param("IMAGE_B", "raster", "Later image", cli="--image-b"),
            Param("DSM_A", "raster", "Surface model, earlier date", cli="--dsm-a", optional=True),
            Param("DSM_B", "raster", "Surface model, later date", cli="--dsm-b", optional=True),
            Param(
                "GROUND",
                "raster",
                "Terrain DEM (default: estimated from the DSMs)",
                cli="--ground",
                optional=True,
                advanced=True,
            ),
            _out_folder(),
            Param(
                "METHOD",
                "enum",
                "Model",
                cli="--method",
                default=0,
                options=(
                    ("joint detection (ED, the paper's)", "ED"),
                    ("each date alone, then compared (SD)", "SD"),
                    ("edge-only verification (EV)", "EV"),
                ),
            ),
            Param(
                "PROTOTYPES",
                "string",
                "Object prototypes (default: chosen from the data; e.g. "
                "gradient|homogeneity|planarity lets a raised planar DSM block stand without an image cue)",
                cli="--prototypes",
                optional=True,
                advanced=True,
            ),
            Param("SEED", "int", "Random seed", cli="--seed", default=0, min=0, advanced=True),
        ),
        outputs=(
            Output("buildings", "BUILDINGS", "vector", "Buildings and rectangles", layers=("buildings", "rectangles")),
            Output("classes", "CLASSES", "raster", "Building classes (unchanged / demolished / new)"),
            Output("quicklook", "QUICKLOOK", "file", "Quick-look (PNG)", load=False),
            Output("summary", "SUMMARY", "file", "Run summary (JSON)", load=False),
        ),
        tags=("buildings", "change detection", "marked point process", "layers"),
    ),
    AlgSpec(
        name="screen",
        display="2-D change screen (scene manifest)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("screen",),
        short_help="Fast first pass over a whole area (Sakurada's grid features with superpixels): the closest "
        "views of the two epochs are projected on the AOI grid and compared cell by cell; vegetation and "
        "shadows seen in both dates are set aside; the threshold and the confidence come from a "
        "no-change pair of views of one epoch. Loads the dissimilarity, the change mask and the changed "
        "regions, styled.",
        params=(
            _MANIFEST,
            _out_folder(),
            *_SCREEN_PARAMS,
            Param(
                "EPOCH_A",
                "string",
                "First epoch (default: the earliest)",
                cli="--epoch-a",
                optional=True,
                advanced=True,
            ),
            Param(
                "EPOCH_B", "string", "Second epoch (default: the latest)", cli="--epoch-b", optional=True, advanced=True
            ),
        ),
        outputs=(
            Output("dissimilarity", "DISSIMILARITY", "raster", "Dissimilarity (2-D screen)"),
            Output("change_mask", "CHANGE_MASK", "raster", "Change mask (2-D screen)"),
            Output("changes", "CHANGES", "vector", "Changed regions (2-D screen)", layers=("changes",)),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        skip_prefixes=("view:",),
        tags=("change detection", "screening", "2d", "superpixels", "cnn"),
    ),
    AlgSpec(
        name="screenrasters",
        display="2-D change screen (two orthoimages)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("screen",),
        short_help="The 2-D change screen of two georeferenced images (orthoimages; the second is resampled onto "
        "the first's grid; different band counts are compared in grey). The threshold comes from a "
        "no-change pair of images, a labelled pair, or a fixed value.",
        params=(
            Param("A", "raster", "Image of the earlier date"),
            Param("B", "raster", "Image of the later date"),
            _out_folder(),
            *_SCREEN_PARAMS,
            Param(
                "NOCHANGE",
                "rasters",
                "No-change pair (two images of one date, same area)",
                cli="--nochange",
                optional=True,
            ),
        ),
        outputs=(
            Output("dissimilarity", "DISSIMILARITY", "raster", "Dissimilarity (2-D screen)"),
            Output("change_mask", "CHANGE_MASK", "raster", "Change mask (2-D screen)"),
            Output("changes", "CHANGES", "vector", "Changed regions (2-D screen)", layers=("changes",)),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        tags=("change detection", "screening", "2d", "orthoimage"),
    ),
    AlgSpec(
        name="consistency",
        display="Self-consistency model from pair-DEMs",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("consistency",),
        short_help="Learns a scene-class self-consistency model (stage 1) from pair-DEMs of a static scene, e.g. the "
        "pair-DEMs of one epoch: how far two pair-DEMs of unchanged ground disagree, as a function of "
        "their matching score. The model (JSON) is what the change test uses to tell change from noise; "
        "it carries over to other scenes of the same class and sensor.",
        params=(
            Param("PAIR_DEMS", "rasters", "Pair-DEMs (from geocd stereo)"),
            Param(
                "OUTPUT_MODEL",
                "file_destination",
                "Self-consistency model",
                cli="--out",
                file_filter="JSON files (*.json)",
            ),
            Param(
                "GROUP_BY",
                "enum",
                "Compare pair-DEMs",
                cli="--group-by",
                default=0,
                options=(("within each epoch (from their tags)", "epoch"), ("all together (one static scene)", "none")),
            ),
            Param(
                "SCENE_CLASS",
                "string",
                "Scene class (e.g. urban, suburban, rural)",
                cli="--scene-class",
                default="",
                optional=True,
            ),
            Param("SENSOR", "string", "Sensor", cli="--sensor", default="", optional=True, advanced=True),
            _CONFIDENCES,
            Param("BINS", "int", "Number of score bins", cli="--bins", default=24, min=4, advanced=True),
            Param(
                "PLOT",
                "file_destination",
                "Scatter and curves plot",
                cli="--plot",
                optional=True,
                file_filter="PNG files (*.png)",
            ),
        ),
        tags=("self-consistency", "model", "uncertainty", "calibration"),
    ),
    AlgSpec(
        name="change",
        display="3-D change from pair-DEMs (layers)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("change",),
        short_help="Stage 2: tests the pair-DEMs of two epochs against a self-consistency model and maps where the "
        "3-D shape changed, at the chosen confidence levels. A DEM may stand for either epoch (e.g. a "
        "lidar DEM before, stereo after). With building footprints, the buildings layer classes each "
        "building collapsed, partly collapsed, lowered, raised, new, unchanged or unobserved (new buildings "
        "outside the footprints too), with its confidence %. Loads the change raster, the change mask and "
        "the changes/buildings layers, styled.",
        params=(
            Param("EPOCH_A", "rasters", "Pair-DEMs, earlier epoch", cli="--pair-dem-a", optional=True),
            Param("EPOCH_B", "rasters", "Pair-DEMs, later epoch", cli="--pair-dem-b", optional=True),
            Param("DEM_A", "raster", "DEM standing for the earlier epoch", cli="--dem-a", optional=True),
            Param("DEM_B", "raster", "DEM standing for the later epoch", cli="--dem-b", optional=True),
            Param(
                "DEM_DATUM",
                "enum",
                "Vertical datum of these DEMs",
                cli="--vertical-datum",
                options=_DATUMS,
                default=0,
                optional=True,
                advanced=True,
            ),
            Param(
                "MODEL",
                "file",
                "Self-consistency model",
                cli="--model",
                extension="json",
                file_filter="JSON files (*.json)",
            ),
            Param("FOOTPRINTS", "vector", "Building footprints", cli="--footprints", optional=True, geometry="polygon"),
            _out_folder(),
            _CONFIDENCES,
            Param(
                "REPORT_CONFIDENCE",
                "number",
                "Confidence for regions and buildings",
                cli="--report-confidence",
                unit="%",
                default=99.0,
                min=50.0,
                max=99.999,
            ),
            Param(
                "COMBINE",
                "enum",
                "Combine the pair comparisons",
                cli="--combine",
                default=0,
                advanced=True,
                options=(("majority", "majority"), ("all", "all"), ("any", "any")),
            ),
            Param(
                "CALIBRATION",
                "enum",
                "Calibrate a model from another scene to these pair-DEMs",
                cli="--calibration",
                default=0,
                advanced=True,
                options=(
                    ("auto (when the model was learned elsewhere)", "auto"),
                    ("always", "pair"),
                    ("never", "none"),
                ),
            ),
        ),
        outputs=_CHANGE_OUTPUTS,
        tags=("change detection", "3d", "buildings", "dem"),
    ),
    AlgSpec(
        name="run",
        display="Full change detection (scene manifest)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("run",),
        short_help="The whole pipeline on a scene manifest: stereo pair-DEMs → self-consistency baseline (learned "
        "here, or a scene-class model) → cross-epoch change test → change raster, change mask, changed "
        "regions and one buildings layer (the footprints, or without them the building objects of the "
        "earlier DSM, and the new buildings: collapsed / partly collapsed / lowered / raised / new / "
        "unchanged / unobserved, confidence %), loaded styled. Also writes run_config.json and "
        "run_summary.json for reproducibility.",
        params=(
            _MANIFEST,
            _out_folder(),
            Param(
                "MODEL",
                "file",
                "Scene-class self-consistency model (optional: learned here)",
                cli="--model",
                optional=True,
                extension="json",
                file_filter="JSON files (*.json)",
            ),
            Param(
                "FOOTPRINTS",
                "vector",
                "Building footprints (default: the manifest's)",
                cli="--footprints",
                optional=True,
                geometry="polygon",
            ),
            _POSTING,
            Param(
                "EPOCH_A", "string", "Earlier epoch (default: the first)", cli="--epoch-a", optional=True, advanced=True
            ),
            Param(
                "EPOCH_B", "string", "Later epoch (default: the last)", cli="--epoch-b", optional=True, advanced=True
            ),
            _CONFIDENCES,
            Param(
                "REPORT_CONFIDENCE",
                "number",
                "Confidence for regions and buildings",
                cli="--report-confidence",
                unit="%",
                optional=True,
                min=50.0,
                max=99.999,
                advanced=True,
                help="Default 99 %.",
            ),
            Param(
                "CONFIG",
                "file",
                "Run configuration (YAML/JSON)",
                cli="--config",
                optional=True,
                advanced=True,
                file_filter="Run configurations (*.json *.yaml *.yml)",
            ),
            Param(
                "SCREEN",
                "bool",
                "Tiered: the 2-D screen first, 3-D work only around the tiles it flags (whole grid when no cheaper)",
                cli="--screen",
                default=False,
                advanced=True,
            ),
            Param(
                "CALIBRATION",
                "enum",
                "Calibrate a scene-class model to this scene's pair-DEMs",
                cli="--calibration",
                default=0,
                optional=True,
                advanced=True,
                cli_default=False,
                options=(
                    ("auto (when the model was learned elsewhere)", "auto"),
                    ("always", "pair"),
                    ("never", "none"),
                ),
            ),
        ),
        outputs=(
            *_CHANGE_OUTPUTS,
            Output("model", "MODEL_OUT", "file", "Self-consistency model (JSON)", load=False),
            Output("summary", "SUMMARY", "file", "Run summary (JSON)", load=False),
        ),
        tags=("change detection", "pipeline", "stereo", "buildings"),
    ),
    AlgSpec(
        name="runlayers",
        display="Full change detection (image layers)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("run",),
        writes_manifest=True,
        short_help="The whole pipeline on images picked in QGIS: epoch A and epoch B images (RPC or frame cameras, "
        "found from the images' tags or sidecars), an optional prior DEM, building footprints and an "
        "AOI. An epoch may be given by a DEM instead of images. The plugin writes the scene manifest "
        "(kept as OUTPUT/scene_from_qgis.json) and runs `geocd run` on it.",
        params=(
            Param("IMAGES_A", "rasters", "Images, earlier epoch (A)", optional=True, manifest="images_a"),
            Param("IMAGES_B", "rasters", "Images, later epoch (B)", optional=True, manifest="images_b"),
            Param(
                "DEM_A",
                "raster",
                "DEM standing for epoch A (instead of images)",
                optional=True,
                manifest="dem_a",
                advanced=True,
            ),
            Param(
                "DEM_B",
                "raster",
                "DEM standing for epoch B (instead of images)",
                optional=True,
                manifest="dem_b",
                advanced=True,
            ),
            Param("DEM", "raster", "Prior DEM (narrows the height search)", optional=True, manifest="dem"),
            Param(
                "DEM_DATUM",
                "enum",
                "Vertical datum of the DEMs",
                options=_DATUMS,
                default=0,
                optional=True,
                manifest="dem_datum",
                advanced=True,
            ),
            Param(
                "FOOTPRINTS", "vector", "Building footprints", optional=True, geometry="polygon", manifest="footprints"
            ),
            Param("AOI", "extent", "Area of interest (default: the images' overlap)", optional=True, manifest="aoi"),
            Param("POSTING", "number", "Grid posting", unit="m", optional=True, min=0.0, manifest="posting"),
            Param(
                "SCENE_CLASS",
                "string",
                "Scene class (e.g. urban)",
                optional=True,
                manifest="scene_class",
                advanced=True,
            ),
            _out_folder(),
            Param(
                "MODEL",
                "file",
                "Scene-class self-consistency model (needed when an epoch has one pair)",
                cli="--model",
                optional=True,
                extension="json",
                file_filter="JSON files (*.json)",
            ),
            _CONFIDENCES,
            Param(
                "REPORT_CONFIDENCE",
                "number",
                "Confidence for regions and buildings",
                cli="--report-confidence",
                unit="%",
                optional=True,
                min=50.0,
                max=99.999,
                advanced=True,
                help="Default 99 %.",
            ),
        ),
        outputs=(
            *_CHANGE_OUTPUTS,
            Output("model", "MODEL_OUT", "file", "Self-consistency model (JSON)", load=False),
            Output("summary", "SUMMARY", "file", "Run summary (JSON)", load=False),
        ),
        tags=("change detection", "pipeline", "stereo", "layers"),
    ),
    AlgSpec(
        name="probchange",
        display="Probability of 3-D change (scene manifest)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("probchange",),
        short_help="Probability that the 3-D structure changed between two epochs of a scene manifest, never "
        "deciding the depth: image patches are compared only within an epoch, so a different sun or "
        "sensor between the epochs raises no false alarm. Loads the change probability (AOI grid), the "
        "binary change at p > threshold and its polygons, styled.",
        params=(
            _MANIFEST,
            _out_folder(),
            Param(
                "VARIANT",
                "enum",
                "Variant",
                cli="--variant",
                default=0,
                options=(
                    ("object space: vertical rays on the AOI grid (satellites)", "objectspace"),
                    ("key frame: rays of a key frame's pixels", "keyframe"),
                ),
            ),
            Param(
                "KEY",
                "string",
                "Key-frame image name (key-frame variant; default: epoch A's first image)",
                cli="--key",
                optional=True,
                advanced=True,
            ),
            Param("EPOCH_A", "string", "First epoch (default: the earliest)", cli="--epoch-a", optional=True),
            Param("EPOCH_B", "string", "Second epoch (default: the latest)", cli="--epoch-b", optional=True),
            Param(
                "IMAGES_A",
                "string",
                "Image names of epoch A to use (comma-separated; default: all)",
                cli="--image-a",
                multiple=True,
                optional=True,
                advanced=True,
            ),
            Param(
                "IMAGES_B",
                "string",
                "Image names of epoch B to use (comma-separated; default: all)",
                cli="--image-b",
                multiple=True,
                optional=True,
                advanced=True,
            ),
            Param(
                "MODEL",
                "enum",
                "Likelihood model",
                cli="--formulation",
                default=0,
                advanced=True,
                options=(
                    ("robust (+ no-consistent-depth hypothesis, visibility test, all pairs)", "robust"),
                    ("thesis (as published)", "thesis"),
                ),
            ),
            Param(
                "PRIOR",
                "number",
                "Prior probability of change",
                cli="--prior",
                optional=True,
                min=0.001,
                max=0.999,
                advanced=True,
                help="Default 0.5.",
            ),
            Param(
                "BINS",
                "int",
                "Depth hypotheses per ray",
                cli="--bins",
                optional=True,
                min=8,
                advanced=True,
                help="Default 128.",
            ),
            Param(
                "SIGMA",
                "number",
                "σ of the depth epoch (0–255 scale; default: estimated)",
                cli="--sigma",
                optional=True,
                min=0.0,
                advanced=True,
            ),
            Param(
                "SIGMA_PRIME",
                "number",
                "σ' of the other epoch (default: estimated)",
                cli="--sigma-prime",
                optional=True,
                min=0.0,
                advanced=True,
            ),
            Param(
                "THRESHOLD",
                "number",
                "Binary change where p > threshold",
                cli="--threshold",
                optional=True,
                min=0.0,
                max=1.0,
                help="Default 0.5.",
            ),
            Param(
                "PAIRS",
                "enum",
                "Pairs within an epoch",
                cli="--pairs",
                default=0,
                advanced=True,
                options=(
                    ("default (star for thesis, all for robust)", ""),
                    ("star", "star"),
                    ("consecutive", "consecutive"),
                    ("all", "all"),
                ),
            ),
            Param(
                "SYMMETRIC", "bool", "Also swap the epochs and combine", cli="--symmetric", default=False, advanced=True
            ),
            Param(
                "HEIGHT_RANGE",
                "range",
                "Height range of the hypotheses (ellipsoidal)",
                cli="--height-range",
                unit="m",
                optional=True,
                advanced=True,
                help="Default: prior DEM − 5 / + 40 m, else the cameras.",
            ),
            _POSTING,
            Param(
                "PREFIX",
                "string",
                "File name prefix of the products",
                cli="--prefix",
                optional=True,
                advanced=True,
                help="Default probchange.",
            ),
        ),
        outputs=(
            Output("probability", "PROBABILITY", "raster", "Probability of 3-D change"),
            Output("change_mask", "CHANGE_MASK", "raster", "Change mask (p > threshold)"),
            Output("changes", "CHANGES", "vector", "Changed regions", layers=("changes",)),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        load_unlisted=True,
        tags=("change detection", "probability", "3d", "illumination"),
    ),
    AlgSpec(
        name="demdiff",
        display="DEM-to-DEM change",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("demdiff",),
        short_help="Height change between two DEMs of the same place (any CRS, vertical datum and posting; B is "
        "resampled onto A's grid), with co-registration on stable terrain and honest uncertainty: "
        "dh = B − A (m), its significance (confidence %, sigma, z), a change mask and the changed "
        "regions (and attributed buildings, with footprints) as polygons. Layers load styled.",
        params=(
            Param("DEM_A", "raster", "DEM A (reference, earlier)"),
            Param("DEM_B", "raster", "DEM B (later)"),
            _out_folder(),
            Param(
                "FOOTPRINTS",
                "vector",
                "Building footprints (excluded from stable terrain; attributed)",
                cli="--footprints",
                optional=True,
                geometry="polygon",
            ),
            Param(
                "STABLE_MASK",
                "file",
                "Stable-terrain mask (raster or polygons; default: automatic)",
                cli="--stable-mask",
                optional=True,
                file_filter="Rasters and vectors (*.tif *.tiff *.gpkg *.shp *.geojson);;All files (*)",
            ),
            Param(
                "MASK_IS",
                "enum",
                "The mask marks",
                cli="--mask-is",
                default=0,
                options=(("stable terrain", "stable"), ("unstable areas (e.g. glacier outlines)", "unstable")),
            ),
            Param(
                "CONFIDENCE",
                "number",
                "Confidence level for 'changed'",
                cli="--confidence",
                unit="%",
                default=95.0,
                min=50.0,
                max=99.999,
                help="A percentage: 95 means 95 %.",
            ),
            Param(
                "BASE",
                "file",
                "Base DEM both DEMs were merged onto (optional)",
                cli="--base",
                optional=True,
                file_filter="DEMs (*.tif *.tiff *.e00 *.vrt *.asc);;All files (*)",
                help="When each DEM is a survey pasted on a common base DEM (e.g. the Mount St Helens archive), "
                "give the base: only cells where both DEMs differ from it (both epochs surveyed) are "
                "compared. Without it the pasted base is identical in both DEMs, the stable terrain is "
                "degenerate (NMAD 0) and geocd warns that σ is not credible.",
            ),
            Param(
                "DATUM_A",
                "enum",
                "Vertical datum of DEM A (when its file does not say)",
                cli="--vertical-datum",
                options=_DATUMS_AB,
                default=0,
                cli_default=False,  # both given in turn: A's, then B's
                optional=True,
                advanced=True,
            ),
            Param(
                "DATUM_B",
                "enum",
                "Vertical datum of DEM B",
                cli="--vertical-datum",
                options=_DATUMS_AB,
                default=0,
                cli_default=False,  # both given in turn: A's, then B's
                optional=True,
                advanced=True,
            ),
            Param(
                "RESAMPLING",
                "enum",
                "Resampling of B onto A's grid",
                cli="--resampling",
                default=1,
                advanced=True,
                options=(("nearest", "nearest"), ("bilinear", "bilinear"), ("cubic", "cubic"), ("average", "average")),
            ),
            Param(
                "NO_COREG",
                "bool",
                "Do not co-register (compare the DEMs as they are)",
                cli="--no-coreg",
                default=False,
                advanced=True,
            ),
            Param("TILT", "bool", "Also remove a planar vertical tilt", cli="--tilt", default=False, advanced=True),
            Param(
                "ON_UNDERCONSTRAINED",
                "enum",
                "When the co-registration fit is under-constrained",
                cli="--on-underconstrained",
                default=0,
                advanced=True,
                options=(
                    ("vertical shift only", "vertical_only"),
                    ("apply it anyway", "apply"),
                    ("do not co-register", "none"),
                    ("fail", "raise"),
                ),
            ),
            Param(
                "MIN_REGION_CELLS",
                "int",
                "Smallest changed region kept",
                cli="--min-region-cells",
                unit="cells",
                default=4,
                min=1,
                advanced=True,
            ),
            Param(
                "REGION_TEST",
                "enum",
                "Region test (minimum mapping unit from the noise model)",
                cli="--region-test",
                default=0,
                advanced=True,
                options=(("noise: drop regions noise alone forms", "noise"), ("off: every region", "off")),
            ),
            Param(
                "FALLBACK_THRESHOLD",
                "number",
                "|dh| marking change when there is no stable terrain",
                cli="--fallback-threshold",
                unit="m",
                optional=True,
                min=0.0,
                advanced=True,
            ),
            Param(
                "PREFIX", "string", "Prefix of the output file names", cli="--prefix", default="demdiff", advanced=True
            ),
            Param("NO_PLOTS", "bool", "Do not draw PNG plots", cli="--no-plots", default=False, advanced=True),
            Param(
                "TILED",
                "bool",
                "Process tile by tile (whole scenes: bounded memory, resumable, on Dask)",
                cli="--tiled",
                default=False,
                advanced=True,
                help="Automatic above 16 million cells. The products are the same as an untiled run's.",
            ),
            _SCHEDULER,
        ),
        outputs=(
            Output("dh", "DH", "raster", "Height change dh = B − A (m)"),
            Output("significance", "SIGNIFICANCE", "raster", "Significance: confidence %, sigma (m), z"),
            Output("change_mask", "CHANGE_MASK", "raster", "Change mask (raised / lowered / unchanged)"),
            Output("changes", "CHANGES", "vector", "Changed regions", layers=("changes", "buildings")),
            Output("report", "REPORT", "file", "Report (JSON: co-registration, uncertainty, volumes)", load=False),
            Output("dh_png", "DH_PNG", "file", "Map of dh (PNG)", load=False),
        ),
        tags=("dem", "difference", "change", "coregistration", "volume"),
    ),
    AlgSpec(
        name="demseries",
        display="DEM time series (volumes)",
        group=GROUP_CHANGE[0],
        group_id=GROUP_CHANGE[1],
        command=("demdiff",),
        short_help="Height change along a series of three or more DEMs of one place (in date order, or with "
        "dates): co-registers each to the first and tabulates the volume gained and lost per interval "
        "with its uncertainty (CSV, JSON, GeoPackage table and a plot). With a base DEM the DEMs were "
        "merged onto, each epoch's survey is where it differs from the base.",
        params=(
            Param("DEMS", "rasters", "DEMs (in date order unless dates are given)"),
            _out_folder(),
            Param("DATES", "string", "Dates of the DEMs (comma-separated YYYY-MM-DD)", cli="--dates", optional=True),
            Param("NAMES", "string", "Epoch names (comma-separated)", cli="--names", optional=True),
            Param(
                "BASE",
                "file",
                "Base DEM the series was merged onto (optional)",
                cli="--base",
                optional=True,
                advanced=True,
            ),
            Param(
                "STABLE_MASK",
                "file",
                "Stable-terrain mask (raster or polygons; default: automatic)",
                cli="--stable-mask",
                optional=True,
                advanced=True,
            ),
            Param(
                "CONFIDENCE",
                "number",
                "Confidence level",
                cli="--confidence",
                unit="%",
                default=95.0,
                min=50.0,
                max=99.999,
                help="A percentage: 95 means 95 %.",
            ),
            Param(
                "PAIR_PRODUCTS",
                "bool",
                "Also write every interval's rasters and layers",
                cli="--pair-products",
                default=False,
            ),
            Param(
                "PREFIX", "string", "Prefix of the output file names", cli="--prefix", default="demdiff", advanced=True
            ),
        ),
        outputs=(
            Output("timeseries_csv", "TABLE", "file", "Volume table (CSV)", load=False),
            Output("timeseries_json", "TABLE_JSON", "file", "Volume table and notes (JSON)", load=False),
            Output("timeseries_png", "PLOT", "file", "Volume plot (PNG)", load=False),
        ),
        load_unlisted=True,
        skip_prefixes=("timeseries_gpkg",),
        tags=("dem", "time series", "volume"),
    ),
    AlgSpec(
        name="volumeupdate",
        display="Volumetric model from images (create/update)",
        group=GROUP_VOLUME[0],
        group_id=GROUP_VOLUME[1],
        command=("volume", "update"),
        short_help="Creates or updates an octree occlusion-density and appearance model of the scene (Crispell et "
        "al.) from images with RPC or frame cameras: the images of a manifest's epoch, or image layers. "
        "The model folder is saved atomically after each pass, so a cancelled update keeps the last "
        "complete pass. Learn from epoch A's images, then detect change in epoch B's images.",
        params=(
            Param("MODEL", "folder_destination", "Model folder (created, or updated when it exists)"),
            Param(
                "MANIFEST",
                "file",
                "Scene manifest (its AOI and DEM define a new model)",
                cli="--manifest",
                optional=True,
                file_filter="Scene manifests (*.yaml *.yml *.json);;All files (*)",
            ),
            Param(
                "EPOCHS",
                "string",
                "Epochs of the manifest to learn from (comma-separated; default: the first)",
                cli="--epoch",
                optional=True,
                multiple=True,
            ),
            Param("IMAGES", "rasters", "Images to learn from instead of the manifest's", cli="--image", optional=True),
            Param(
                "EXCLUDE",
                "string",
                "Image names to leave out (comma-separated)",
                cli="--exclude",
                optional=True,
                multiple=True,
                advanced=True,
            ),
            Param("PASSES", "int", "Passes over the images", cli="--passes", default=5, min=1),
            Param(
                "FINEST_CELL",
                "number",
                "Finest octree cell edge (new models)",
                cli="--finest-cell",
                unit="m",
                default=0.5,
                min=0.01,
            ),
            Param(
                "MAX_DEPTH",
                "int",
                "Octree levels below a block (new models)",
                cli="--max-depth",
                default=3,
                min=0,
                max=8,
                advanced=True,
            ),
            Param(
                "INIT_DEPTH",
                "int",
                "Initial refinement level (new models)",
                cli="--init-depth",
                default=1,
                min=0,
                max=8,
                advanced=True,
            ),
            Param(
                "ABOVE",
                "number",
                "Volume top above the DEM's highest point (new models)",
                cli="--above",
                unit="m",
                default=30.0,
                min=0.0,
                advanced=True,
            ),
            Param(
                "FIXED_GRID",
                "bool",
                "Fixed grid at the finest level (no refinement)",
                cli="--fixed-grid",
                default=False,
                advanced=True,
            ),
            Param(
                "FOOTPRINTS",
                "bool",
                "Roof heights from the manifest's footprints in the prior (new models)",
                cli="--roofs-from-footprints",
                default=False,
                advanced=True,
            ),
            Param(
                "SUPERSAMPLE", "int", "Rays per pixel side", cli="--supersample", default=1, min=1, max=8, advanced=True
            ),
            Param(
                "NORMALIZE",
                "enum",
                "Radiometric normalisation",
                cli="--normalize",
                default=0,
                advanced=True,
                options=(("equalize", "equalize"), ("percentile", "percentile"), ("scale", "scale")),
            ),
            Param(
                "SUN",
                "pair",
                "Sun azimuth, elevation of all images (when their metadata lacks it)",
                cli="--sun",
                unit="°",
                optional=True,
                advanced=True,
            ),
            Param("SEED", "int", "Seed of the image order", cli="--seed", default=0, advanced=True),
        ),
        outputs=(Output("model", "MODEL_OUT", "folder", "Model folder", load=False),),
        tags=("volumetric", "octree", "voxel", "3d", "appearance"),
    ),
    AlgSpec(
        name="volumedetect",
        display="Volumetric change probability of an image",
        group=GROUP_VOLUME[0],
        group_id=GROUP_VOLUME[1],
        command=("volume", "detect"),
        short_help="Probability that each pixel of a new image shows a change against the volumetric model "
        "(Crispell et al., eq. 27), in the image's geometry and orthorectified on the model's expected "
        "height map. Both rasters load with a 0–1 probability ramp.",
        params=(
            Param("MODEL", "folder", "Model folder (from 'learn from images')"),
            Param("IMAGE", "raster", "Image to test"),
            Param(
                "CAMERA",
                "file",
                "Camera file of the image (default: found next to it)",
                cli="--camera",
                optional=True,
                advanced=True,
            ),
            _out_folder(),
            Param(
                "NEIGHBORHOOD",
                "int",
                "n of the n×n neighbourhood variant (odd; 1 = plain eq. 27)",
                cli="--neighborhood",
                default=3,
                min=1,
                max=15,
            ),
            Param("PRIOR", "number", "Prior probability of change", cli="--prior", default=0.5, min=0.001, max=0.999),
            Param(
                "NO_RELIGHT",
                "bool",
                "Use the nearest sun bin's appearance as is (no relighting)",
                cli="--no-relight",
                default=False,
                advanced=True,
            ),
            Param(
                "SHADOW_DSM",
                "raster",
                "DSM of the model's training epoch (e.g. geocd stereo's): a relit image's shadows are cast from it",
                cli="--shadow-dsm",
                optional=True,
            ),
            Param(
                "POSTING",
                "number",
                "Posting of the orthorectified output (default: the finest cell)",
                cli="--posting",
                unit="m",
                optional=True,
                min=0.0,
                advanced=True,
            ),
            Param(
                "NORMALIZE",
                "enum",
                "Radiometric normalisation",
                cli="--normalize",
                default=0,
                advanced=True,
                options=(("equalize", "equalize"), ("percentile", "percentile"), ("scale", "scale")),
            ),
            Param(
                "SUN",
                "pair",
                "Sun azimuth, elevation of the image",
                cli="--sun",
                unit="°",
                optional=True,
                advanced=True,
            ),
        ),
        outputs=(
            Output(
                "change_probability_ortho",
                "PROBABILITY_ORTHO",
                "raster",
                "Change probability (orthorectified)",
                style="auto:probability",
            ),
            Output(
                "change_probability",
                "PROBABILITY",
                "raster",
                "Change probability, expected intensity, visibility (image geometry)",
                style="auto:probability",
            ),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        tags=("volumetric", "change detection", "probability"),
    ),
    AlgSpec(
        name="volumerender",
        display="Volumetric rendering: expected images, height map",
        group=GROUP_VOLUME[0],
        group_id=GROUP_VOLUME[1],
        command=("volume", "render"),
        short_help="Renders what the volumetric model expects: the image of each given view, and/or its expected "
        "height map (ellipsoidal heights, Cloud-Optimized GeoTIFF).",
        params=(
            Param("MODEL", "folder", "Model folder"),
            Param("IMAGES", "rasters", "Views to render (their cameras)", cli="--image", optional=True),
            Param("HEIGHT_MAP", "bool", "Expected height map", cli="--height-map", default=True, cli_default=False),
            Param("POSTING", "number", "Height-map posting", cli="--posting", unit="m", optional=True, min=0.0),
            _out_folder(),
        ),
        outputs=(
            Output("height_map", "HEIGHT_MAP", "raster", "Expected height map (ellipsoidal, m)", style="auto:height"),
        ),
        load_unlisted=True,
        tags=("volumetric", "render", "dem"),
    ),
    AlgSpec(
        name="landcovertrain",
        display="Land cover: train a pixel classifier",
        group=GROUP_LANDCOVER[0],
        group_id=GROUP_LANDCOVER[1],
        command=("landcover", "train"),
        short_help="Trains a pixel classifier (random forest; logistic regression or SVM for comparison) on local "
        "features — Lab colour, 5×5 grey mean and variance, scikit-image texture, optionally the height "
        "above ground — from polygons you drew with a class attribute (e.g. 'vegetation' and "
        "'other'): on the map (they reach raw images through their cameras and the DEM) or on an "
        "image in pixel coordinates. Writes a reusable model (.joblib) and a JSON report.",
        params=(
            Param("LABELS", "vector", "Label polygons (class attribute)", cli="--labels", geometry="polygon"),
            Param(
                "CLASS_FIELD",
                "string",
                "Class attribute (default: class, label, landcover, ...)",
                cli="--class-field",
                optional=True,
            ),
            Param("POSITIVE", "string", "The condition's class (e.g. vegetation)", cli="--positive", optional=True),
            Param("IMAGES", "rasters", "Images to learn from (one sensor per model)", cli="--image"),
            Param(
                "METHOD",
                "enum",
                "Classifier",
                cli="--method",
                default=0,
                options=(("random forest", "rf"), ("logistic regression", "logreg"), ("SVM (RBF)", "svm")),
            ),
            Param(
                "COMPARE",
                "bool",
                "Also cross-validate all three methods (holding out whole polygons)",
                cli="--compare",
                default=False,
                advanced=True,
            ),
            Param(
                "HEIGHT_ABOVE_GROUND",
                "bool",
                "Height above ground as a feature (needs a DSM or footprints)",
                cli="--height-above-ground",
                default=False,
                advanced=True,
            ),
            *_LANDCOVER_SCENE,
            Param("SEED", "int", "Random seed", cli="--seed", default=0, advanced=True),
            Param("MODEL_FILE", "file_destination", "Model file", cli="--out", file_filter="Models (*.joblib)"),
        ),
        outputs=(
            Output("model", "MODEL", "file", "Model (.joblib)", load=False),
            Output("report", "REPORT", "file", "Training report (JSON)", load=False),
        ),
        tags=("land cover", "classification", "random forest", "vegetation", "debris"),
    ),
    AlgSpec(
        name="landcoverpredict",
        display="Land cover: probability maps (images and ground)",
        group=GROUP_LANDCOVER[0],
        group_id=GROUP_LANDCOVER[1],
        command=("landcover", "predict"),
        short_help="Applies a land-cover model to images: a probability map per image (image geometry) and, with a "
        "DEM or manifest, the condition's probability on the ground grid — each image projected through "
        "its camera and the surface (footprints extruded or a DSM): cells hidden behind buildings stay "
        "empty, several views are combined by weight.",
        params=(
            Param(
                "MODEL",
                "file",
                "Model (from 'train a pixel classifier')",
                cli="--model",
                file_filter="Models (*.joblib);;All files (*)",
            ),
            Param(
                "TRUST_MODEL",
                "bool",
                "Trust a model file trained elsewhere (loading a model runs any code its "
                "author put in it: only for files from people you trust)",
                cli="--trust-model",
                default=False,
                advanced=True,
            ),
            Param("IMAGES", "rasters", "Images to classify", cli="--image"),
            Param("CLASS", "string", "Class to project (default: the positive class)", cli="--class", optional=True),
            *_LANDCOVER_SCENE,
            _out_folder(),
        ),
        outputs=(
            Output(
                "ground",
                "GROUND",
                "raster",
                "Probability on the ground (weighted over views)",
                style="auto:probability",
            ),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        load_unlisted=True,
        tags=("land cover", "classification", "orthorectification", "probability"),
    ),
    AlgSpec(
        name="landcoverintegrate",
        display="Land cover: city-scale GP integration",
        group=GROUP_LANDCOVER[0],
        group_id=GROUP_LANDCOVER[1],
        command=("landcover", "integrate"),
        short_help="Gaussian-process regression (Sakurada) of the detailed views' probability over every cell, "
        "with the cells' position, DEM height, a coarse full-cover probability and building occupancy "
        "as inputs (ARD kernel: one length scale per input; hyperparameters by exact GP on a subsample, "
        "prediction with inducing points, so a million cells run in bounded memory). Writes the "
        "predictive mean and σ; with a truth raster also the ablation report (PR curves, F1 at recall "
        "0.5, σ calibration).",
        params=(
            Param(
                "DETAILED", "raster", "Detailed views' probability on the ground (NaN = unobserved)", cli="--detailed"
            ),
            Param(
                "COARSE",
                "raster",
                "Coarse full-cover probability (e.g. the satellite image's)",
                cli="--coarse",
                optional=True,
            ),
            Param(
                "INPUTS",
                "string",
                "GP inputs (comma-separated from xy, dem, coarse, buildings; default: all available)",
                cli="--inputs",
                optional=True,
                advanced=True,
            ),
            Param("CLASS_NAME", "string", "Name of the condition", cli="--class-name", default="condition"),
            Param(
                "KERNEL",
                "enum",
                "Kernel",
                cli="--kernel",
                default=0,
                advanced=True,
                options=(
                    ("additive: position + appearance (carries appearance at any distance)", "additive"),
                    ("product: one ARD kernel over every input (thesis)", "product"),
                ),
            ),
            Param(
                "N_FIT",
                "int",
                "Cells for the exact-GP hyperparameter fit",
                cli="--n-fit",
                default=1000,
                min=10,
                advanced=True,
            ),
            Param("INDUCING", "int", "Inducing points", cli="--inducing", default=400, min=1, advanced=True),
            Param(
                "BATCH",
                "int",
                "Cells per prediction batch (memory)",
                cli="--batch",
                default=20000,
                min=1,
                advanced=True,
            ),
            Param(
                "CALIBRATE_FOLDS",
                "int",
                "Spatial blocks held out to calibrate σ (0 = off)",
                cli="--calibrate-folds",
                default=0,
                min=0,
                advanced=True,
            ),
            Param("SEED", "int", "Random seed", cli="--seed", default=0, advanced=True),
            Param(
                "TRUTH",
                "raster",
                "Truth raster (adds the ablation report)",
                cli="--truth",
                optional=True,
                advanced=True,
            ),
            Param(
                "TRUTH_VALUES",
                "string",
                "Truth codes meaning the condition (comma-separated; default nonzero)",
                cli="--truth-values",
                optional=True,
                advanced=True,
            ),
            Param(
                "EXCLUDE_LABELS",
                "vector",
                "Training labels (left out of the ablation scores)",
                cli="--exclude-labels",
                optional=True,
                geometry="polygon",
                advanced=True,
            ),
            *_LANDCOVER_SCENE,
            _out_folder(),
        ),
        outputs=(
            Output("probability", "PROBABILITY", "raster", "GP mean probability", style="auto:probability"),
            Output("sigma", "SIGMA", "raster", "GP σ, σ of a new observation, unclipped mean, detailed input"),
            Output("ablation", "ABLATION", "file", "Ablation report (JSON)", load=False),
            Output("ablation_png", "ABLATION_PNG", "file", "PR curves and F1 at recall 0.5 (PNG)", load=False),
            Output("summary", "SUMMARY", "file", "Summary (JSON)", load=False),
        ),
        tags=("land cover", "gaussian process", "regression", "vegetation", "debris", "uncertainty"),
    ),
    AlgSpec(
        name="synth",
        display="Synthetic test scene",
        group=GROUP_DATA[0],
        group_id=GROUP_DATA[1],
        command=("synth",),
        short_help="Generates a synthetic town with two epochs, satellite (RPC) and aerial (frame) views and exact "
        "truth (DSMs, change masks, footprints): a scene folder with scene.yaml that every geocd "
        "algorithm accepts. Seed 0 with the defaults regenerates geocd's sample_aoi.",
        params=(
            _out_folder("The scene folder (must be empty unless 'Replace' is ticked)."),
            Param("SEED", "int", "Random seed", cli="--seed", default=0),
            Param(
                "TINY",
                "bool",
                "Tiny preset (64 m, 2+2 satellite views, 2 frames; for tests)",
                cli="--tiny",
                default=False,
            ),
            Param(
                "SIZE_M",
                "number",
                "Side of the square AOI",
                cli="--size",
                unit="m",
                default=300.0,
                min=16.0,
                advanced=True,
            ),
            Param(
                "GSD_M",
                "number",
                "Satellite ground sampling distance",
                cli="--gsd",
                unit="m",
                default=0.5,
                min=0.05,
                advanced=True,
            ),
            Param(
                "POSTING_M",
                "number",
                "Truth grid posting",
                cli="--posting",
                unit="m",
                default=0.5,
                min=0.05,
                advanced=True,
            ),
            Param("N_SAT_A", "int", "Satellite views, epoch A", cli="--n-sat-a", default=4, min=0, advanced=True),
            Param("N_SAT_B", "int", "Satellite views, epoch B", cli="--n-sat-b", default=3, min=0, advanced=True),
            Param("N_AERIAL", "int", "Aerial frames, epoch A", cli="--n-aerial", default=3, min=0, advanced=True),
            Param(
                "CHANGES",
                "string",
                "Change types (comma-separated; empty = all)",
                cli="--changes",
                optional=True,
                advanced=True,
                help="new, demolished, raised, lowered, cars, trees, repaint, season.",
            ),
            Param(
                "SAME_SUN", "bool", "Render epoch B under epoch A's sun", cli="--same-sun", default=False, advanced=True
            ),
            Param(
                "SUPERSAMPLE", "int", "Rays per pixel side", cli="--supersample", default=2, min=1, max=8, advanced=True
            ),
            Param("NAME", "string", "Scene name", cli="--name", optional=True, advanced=True),
            Param(
                "OVERWRITE",
                "bool",
                "Replace the files of an existing scene folder",
                cli="--overwrite",
                default=False,
                advanced=True,
            ),
        ),
        outputs=(
            Output("manifest", "SCENE", "file", "Scene manifest (scene.yaml)", load=False),
            Output("report", "REPORT", "file", "Truth report (JSON)", load=False),
        ),
        tags=("synthetic", "simulation", "test data"),
    ),
)


def spec(name: str) -> AlgSpec:
    for s in ALGORITHMS:
        if s.name == name:
            return s
    raise KeyError(name)


def active() -> tuple[AlgSpec, ...]:
    """The algorithms the provider offers (those whose geocd command exists)."""
    return tuple(s for s in ALGORITHMS if not s.pending)


# ---------------------------------------------------------------------------------------------------------------
# plain values → command line / manifest (pure: values are already resolved from the QGIS parameters)
# ---------------------------------------------------------------------------------------------------------------


def _fmt_number(v: Any) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)


def _empty(v: Any) -> bool:
    return v is None or (isinstance(v, str) and v.strip() == "") or (isinstance(v, (list, tuple)) and not v)


def build_args(alg: AlgSpec, values: dict, manifest_path: Optional[str] = None) -> list[str]:
    """geocd arguments after the global options: ``[command..., options..., "--", positionals...]``.

    ``values`` maps parameter names to plain values (paths as str, numbers, bools, enum index, CRS string,
    range as (min, max), lists of paths); ``None`` or missing means "not given" (the CLI default applies).
    """
    positional: list[str] = [manifest_path] if manifest_path else []
    options: list[str] = []
    for p in alg.params:
        if p.manifest:
            continue
        v = values.get(p.name)
        if _empty(v):
            if not p.optional and p.cli is None:
                raise ValueError(f"parameter {p.name} ({p.label}) is required")
            continue
        if p.cli_default and p.default is not None and v == p.default and p.cli is not None:
            continue
        if p.kind == "bool":
            if v and p.cli:
                options.append(p.cli)
            continue
        if p.kind == "enum":
            value = p.options[int(v)][1]
            if value == "":
                continue
            tokens = [[value]]
        elif p.kind == "range":
            lo, hi = v
            if lo is None or hi is None:
                continue
            tokens = [[_fmt_number(lo), _fmt_number(hi)]]
        elif p.kind == "pair":
            items = v if isinstance(v, (list, tuple)) else [x for x in str(v).replace(";", ",").split(",") if x.strip()]
            try:
                if len(items) != 2:
                    raise ValueError
                tokens = [[_fmt_number(items[0]), _fmt_number(items[1])]]
            except ValueError as exc:
                raise ValueError(f"{p.label}: give two numbers separated by a comma, got {v!r}") from exc
        elif p.kind == "number":
            tokens = [[_fmt_number(v)]]
        elif p.kind == "int":
            tokens = [[str(int(v))]]
        elif p.kind == "numbers":
            items = v if isinstance(v, (list, tuple)) else [s for s in str(v).replace(";", ",").split(",") if s.strip()]
            try:
                tokens = [[_fmt_number(x)] for x in items]
            except ValueError as exc:
                raise ValueError(f"{p.label}: give numbers separated by commas, got {v!r}") from exc
        elif p.kind == "string" and p.multiple:
            tokens = [[s.strip()] for s in str(v).split(",") if s.strip()]
        elif p.kind == "rasters":
            tokens = [[str(x)] for x in v]
        else:
            tokens = [[str(v)]]
        for t in tokens:
            if p.cli is None:
                positional += t
            else:
                options += [p.cli, *t]
    # "--" ends the options, so a positional path that starts with "-" is not read as an option
    return [*alg.command, *alg.fixed_args, *options, *(["--", *positional] if positional else [])]


def _dem_entry(path: str, datum: Optional[str]) -> Any:
    return {"path": path, "vertical_datum": datum} if datum else path


def _vector_entry(path: str) -> Any:
    """``file.gpkg|layername=x`` (QGIS source) → ``{path, layer}`` (manifest)."""
    if "|layername=" in path:
        p, rest = path.split("|layername=", 1)
        return {"path": p, "layer": rest.split("|", 1)[0]}
    return path.split("|", 1)[0]


def build_manifest(alg: AlgSpec, values: dict, name: str = "qgis_layers", output: Optional[str] = None) -> dict:
    """A geocd scene manifest (``geocd_manifest: 1``, see geocd/io/manifest.py) from the ``manifest`` parameters.

    Roles: images_a / images_b (one path or a list; images_a alone = one epoch), dem_a / dem_b (a DEM standing
    for an epoch), dem (prior DEM), dem_datum (CLI value of the datum enum), footprints (vector path), aoi
    ((xmin, ymin, xmax, ymax, crs)), posting (m), scene_class.
    """
    roles: dict[str, Any] = {}
    datum_param = next((p for p in alg.params if p.manifest == "dem_datum"), None)
    for p in alg.params:
        if not p.manifest:
            continue
        v = values.get(p.name)
        if _empty(v):
            continue
        if p.manifest in ("images_a", "images_b"):
            roles.setdefault(p.manifest, []).extend(v if isinstance(v, (list, tuple)) else [v])
        else:
            roles[p.manifest] = v
    datum = None
    if datum_param is not None and roles.get("dem_datum") is not None:
        datum = datum_param.options[int(roles["dem_datum"])][1] or None
    m: dict[str, Any] = {"geocd_manifest": 1, "name": name}
    if roles.get("scene_class"):
        m["scene_class"] = str(roles["scene_class"])
    aoi: dict[str, Any] = {}
    if roles.get("aoi"):
        xmin, ymin, xmax, ymax, crs = roles["aoi"]
        aoi.update({"crs": crs, "bounds": [float(xmin), float(ymin), float(xmax), float(ymax)]})
    if roles.get("posting"):
        aoi["posting_m"] = float(roles["posting"])
    if aoi:
        m["aoi"] = aoi
    if output:
        m["output"] = output
    if roles.get("dem"):
        m["dem"] = _dem_entry(roles["dem"], datum)
    if roles.get("footprints"):
        m["footprints"] = _vector_entry(roles["footprints"])
    epochs = []
    for ep, img_role, dem_role in (("A", "images_a", "dem_a"), ("B", "images_b", "dem_b")):
        imgs = roles.get(img_role, [])
        dem = roles.get(dem_role)
        if not imgs and not dem:
            continue
        e: dict[str, Any] = {
            "name": ep,
            "images": [{"path": str(i), "name": _image_name(str(i), k, imgs)} for k, i in enumerate(imgs)],
        }
        if dem:
            e["dem"] = _dem_entry(dem, datum)
        epochs.append(e)
    if not epochs:
        raise ValueError("give images (or a DEM) for at least one epoch")
    m["epochs"] = epochs
    return m


def _image_name(path: str, k: int, all_paths: list) -> str:
    import os

    stem = os.path.splitext(os.path.basename(path))[0] or f"image{k + 1}"
    stems = [os.path.splitext(os.path.basename(str(p)))[0] for p in all_paths]
    return stem if stems.count(stem) == 1 else f"{stem}_{k + 1}"
