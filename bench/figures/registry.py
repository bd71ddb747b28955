"""Every picture README.md and docs/ show, and the commands that make it from a fresh run.

One :class:`Entry` per figure script run (one entry may write several pictures). Steps are argument lists run from
the repository root, with these placeholders:

* ``{python}`` — the Python running ``bench.figures`` (geocd's virtual environment);
* ``{geocd}`` — ``{python} -m geocd --progress none``;
* ``{qgis_python}`` — the system Python that has PyQGIS (``/usr/bin/python3``);
* ``{work}`` — the figures' work folder (``--work``); an entry writes under ``{work}/<its name>``, and reads
  what the entries it ``needs`` wrote under theirs;
* ``{docs}`` — ``docs/``; ``{data}`` — ``../shared/data`` (or ``$GEOCD_SHARED_DATA``);
* ``{repo}`` — the repository root.

A step ``("copy", SRC, DST)`` copies a file (a run's own product into ``docs/``). ``minutes`` is the wall time
of the whole entry on the 2-core development host (``measured`` says whether it was timed by ``python -m
bench.figures``; else an estimate from the page that quotes the figure); ``cost`` is ``quick`` (a few minutes:
``--quick`` runs these), ``long`` (up to about an hour) or ``slow`` (hours). An entry whose ``script`` is None has
no script yet: ``--list`` shows the gap.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: what a step can be: a command (argument list) or ("copy", SRC, DST)
Step = tuple[str, ...]


@dataclass(frozen=True)
class Entry:
    """One figure script run: the pictures it writes, what they show, how to make them and what that needs.

    Attributes
    ----------
    name : str
        The entry's name (``--only NAME``).
    pictures : tuple of str
        The PNGs it writes under ``docs/`` (file names); empty for an entry others need (a run).
    shows : str
        What the pictures show (their caption's substance).
    script : str or None
        The script that draws them (path from the repository root); None: no script yet.
    steps : tuple of Step
        The commands, in order (placeholders: see the module's docstring).
    data : tuple of str
        Folders of ``../shared/data`` it reads ("" when it reads only the repository).
    tools : tuple of str
        Programs beyond geocd's environment: ``qgis`` (PyQGIS and ``qgis_process``), ``xvfb-run``, ``cars``.
    needs : tuple of str
        Entries whose work folder it reads (run first, once per invocation).
    cost : str
        ``quick``, ``long`` or ``slow``.
    minutes : float
        Wall minutes on the 2-core development host.
    measured : bool
        ``minutes`` was timed by ``python -m bench.figures`` (else an estimate).
    env : dict
        Environment variables for its steps.
    note : str
        Anything the list should say about it.
    tables : tuple of str
        Generated tables it rewrites instead of pictures (where, from what), e.g. the README's table against peers.
    """

    name: str
    pictures: tuple[str, ...]
    shows: str
    script: str | None
    steps: tuple[Step, ...] = ()
    data: tuple[str, ...] = ()
    tools: tuple[str, ...] = ()
    needs: tuple[str, ...] = ()
    cost: str = "quick"
    minutes: float = 1.0
    measured: bool = False
    env: dict = field(default_factory=dict)
    note: str = ""
    tables: tuple[str, ...] = ()


def _cmd(line: str) -> Step:
    return tuple(line.split())


KAHRA = "{work}/kahramanmaras_run/run"
MSH = "{data}/usgs_msh_dome_dems/geotiff_utm10n"
QGIS_ENV = {"QT_QPA_PLATFORM": "offscreen", "GEOCD_EXECUTABLE": "{python_bin}/geocd", "GDAL_PAM_ENABLED": "NO"}

ENTRIES: tuple[Entry, ...] = (
    # ------------------------------------------------------------------ the runs' own quick-looks
    Entry(
        "sample_aoi_run",
        ("sample_aoi_change.png",),
        "what `geocd run sample_aoi` finds: the run's own quick-look (sc_quicklook.png): epoch A | epoch B | "
        "the buildings by class at 99 % with the count of each class",
        "geocd run (geocd/change/plots.py: change_quicklook_figure)",
        (
            _cmd("{geocd} run sample_aoi --out {work}/sample_aoi_run/run"),
            ("copy", "{work}/sample_aoi_run/run/sc_quicklook.png", "{docs}/sample_aoi_change.png"),
        ),
        minutes=2.2,
        measured=True,
    ),
    Entry(
        "kahramanmaras_run",
        ("kahramanmaras_quicklook.png",),
        "the run's own quick-look of the tutorial's run: pre-event | post-event (orthos of each epoch's first "
        "view) | the damage classes at 99 % with the count of each class (= run_summary.json)",
        "geocd run (geocd/change/plots.py: change_quicklook_figure)",
        (
            _cmd(
                "{geocd} run examples/kahramanmaras/scene.yaml --model "
                "examples/kahramanmaras/marseille_urban_model.json --out " + KAHRA
            ),
            ("copy", KAHRA + "/sc_quicklook.png", "{docs}/kahramanmaras_quicklook.png"),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        minutes=1.3,
        measured=True,
    ),
    Entry(
        "sample_aoi_epochs",
        ("sample_aoi_epoch_A.png", "sample_aoi_epoch_B.png"),
        "the committed scene's images: one satellite view (and one aerial frame in A) per epoch, with their sun",
        "bench/figures/sample_aoi_epochs.py",
        (_cmd("{python} bench/figures/sample_aoi_epochs.py --out {docs}"),),
        minutes=0.2,
        measured=True,
    ),
    # ------------------------------------------------------------------ QGIS
    Entry(
        "qgis_toolbox",
        ("qgis_toolbox.png", "qgis_dialog.png"),
        "the QGIS desktop (real GUI under a virtual X server): the Processing toolbox filtered on geocd "
        "(every algorithm of the provider) after geocd:demdiff on Mount St Helens loaded its layers styled; "
        "then the algorithm's dialog after a run, geocd's progress in its log",
        "bench/figures/qgis_gui_screenshot.py",
        (
            (
                "xvfb-run",
                "-a",
                "-s",
                "-screen 0 1600x1000x24",
                "/usr/bin/qgis.bin",
                "--nologo",
                "--noversioncheck",
                "--code",
                "bench/figures/qgis_gui_screenshot.py",
            ),
        ),
        data=("usgs_msh_dome_dems",),
        tools=("qgis", "xvfb-run"),
        env={
            **QGIS_ENV,
            "QT_QPA_PLATFORM": "xcb",
            "GEOCD_SHOT_ALG": "geocd:demdiff",
            "GEOCD_SHOT_PARAMS": f"DEM_A={MSH}/2.tif;DEM_B={MSH}/27.tif",
            "GEOCD_SHOT_HIDE": "Significance: confidence %, sigma (m), z;Change mask (raised / lowered / unchanged)",
            "GEOCD_SHOT_BACKDROP": f"{MSH}/27.tif",
            "GEOCD_SHOT_DIR": "{docs}",
            "QGIS_PLUGINPATH": "{repo}/qgis_plugin",
            "QGIS_CUSTOM_CONFIG_PATH": "{work}/qgis_toolbox/profile",
        },
        minutes=0.7,
        measured=True,
    ),
    Entry(
        "qgis_msh_demdiff",
        ("qgis_msh_demdiff.png",),
        "geocd:demdiff run in headless QGIS on Mount St Helens DEMs 2 and 27, its layers rendered by QGIS "
        "with their styles over a hillshade of DEM 27",
        "bench/figures/qgis_screenshot.py",
        (
            (
                "{qgis_python}",
                "bench/figures/qgis_screenshot.py",
                "--alg",
                "geocd:demdiff",
                "--param",
                f"DEM_A={MSH}/2.tif",
                "--param",
                f"DEM_B={MSH}/27.tif",
                "--backdrop",
                f"{MSH}/27.tif",
                "--hide",
                "Change mask (raised / lowered / unchanged)",
                "--hide",
                "Significance: confidence %, sigma (m), z",
                "--title",
                "Mount St Helens dome growth, 2004-10-04 → 2007-07-05 (geocd:demdiff run in QGIS)",
                "--workdir",
                "{work}/qgis_msh_demdiff/run",
                "--out",
                "{docs}/qgis_msh_demdiff.png",
            ),
        ),
        data=("usgs_msh_dome_dems",),
        tools=("qgis",),
        env=QGIS_ENV,
        minutes=0.3,
        measured=True,
    ),
    Entry(
        "qgis_sample_aoi_full",
        ("qgis_sample_aoi_full.png",),
        "geocd:run on the whole sample_aoi in headless QGIS: the buildings by class and the changed regions at "
        "99 % over band 4 of sc_change.tif (the region's confidence, classes 90 / 95 / 99 %), rendered by QGIS",
        "bench/figures/qgis_screenshot.py",
        (
            (
                "{qgis_python}",
                "bench/figures/qgis_screenshot.py",
                "--alg",
                "geocd:run",
                "--param",
                "MANIFEST=sample_aoi/scene.yaml",
                "--hide",
                "Change mask (raised / lowered / unchanged)",
                "--title",
                "sample_aoi: 3-D change A → B (geocd:run in QGIS)",
                "--workdir",
                "{work}/qgis_sample_aoi_full/run",
                "--out",
                "{docs}/qgis_sample_aoi_full.png",
            ),
        ),
        tools=("qgis",),
        env=QGIS_ENV,
        minutes=1.8,
        measured=True,
    ),
    Entry(
        "qgis_sample_aoi_change",
        ("qgis_sample_aoi_change.png",),
        "geocd:runlayers on a 100 m crop of sample_aoi (3 + 3 satellite images) in headless QGIS, rendered by QGIS",
        "bench/figures/qgis_screenshot.py",
        (
            (
                "{qgis_python}",
                "bench/figures/qgis_screenshot.py",
                "--alg",
                "geocd:runlayers",
                *(f"--param=IMAGES_{e}=sample_aoi/images/{e}_sat{i}.tif" for e in "AB" for i in (1, 2, 3)),
                "--param",
                "DEM=sample_aoi/truth/dem_prior.tif",
                "--param",
                "DEM_DATUM=1",
                "--param",
                "FOOTPRINTS=sample_aoi/truth/footprints_all.gpkg",
                "--param",
                "AOI=374344,374444,4824244,4824344 [EPSG:32631]",
                "--hide",
                "Change mask (raised / lowered / unchanged)",
                "--title",
                "sample_aoi, 100 m crop: 3-D change A → B (geocd:runlayers run in QGIS)",
                "--workdir",
                "{work}/qgis_sample_aoi_change/run",
                "--out",
                "{docs}/qgis_sample_aoi_change.png",
            ),
        ),
        tools=("qgis",),
        env=QGIS_ENV,
        minutes=0.6,
        measured=True,
    ),
    Entry(
        "kahramanmaras_orthos",
        (),
        "true orthos of the Kahramanmaraş run (RUN/orthos, RUN/orthos_ground) and bench/results/kahramanmaras_show.json",
        "bench/figures/kahramanmaras_show.py",
        (_cmd("{python} bench/figures/kahramanmaras_show.py --run " + KAHRA),),
        data=("cnes_picanteo_kahramanmaras",),
        needs=("kahramanmaras_run",),
        minutes=0.6,
        measured=True,
    ),
    Entry(
        "qgis_kahramanmaras",
        ("qgis_kahramanmaras.png",),
        "the Kahramanmaraş run's building layer (damage classes) over the post-event ortho, styled layers rendered "
        "by headless QGIS, legend added",
        "bench/figures/qgis_layers_screenshot.py",
        (
            (
                "{qgis_python}",
                "bench/figures/qgis_layers_screenshot.py",
                "--layer",
                KAHRA + "/sc_changes.gpkg|layername=buildings",
                "--layer",
                KAHRA + "/orthos_ground/post_event_img1.tif",
                "--out",
                "{work}/qgis_kahramanmaras/map.png",
            ),
            (
                "{python}",
                "bench/figures/qgis_layers_screenshot.py",
                "--legend",
                "{work}/qgis_kahramanmaras/map.png",
                "{docs}/qgis_kahramanmaras.png",
                "--counts",
                KAHRA + "/sc_changes.gpkg",
                "--title",
                "Kahramanmaraş: building damage (geocd run, styled layers rendered by QGIS)",
            ),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        tools=("qgis",),
        needs=("kahramanmaras_orthos",),
        env=QGIS_ENV,
        minutes=0.2,
        measured=True,
    ),
    # ------------------------------------------------------------------ Kahramanmaraş analyses
    Entry(
        "kahramanmaras_classes",
        ("kahramanmaras_classes.png",),
        "the largest buildings of each class of the run's building layer: pre | post orthos with the outline | "
        "every object nearby in its class colour",
        "bench/figures/kahramanmaras_classes.py",
        (
            _cmd(
                "{python} bench/figures/kahramanmaras_classes.py --run "
                + KAHRA
                + " --per-class 2 --out {docs}/kahramanmaras_classes.png"
            ),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        needs=("kahramanmaras_orthos",),
        minutes=0.2,
    ),
    Entry(
        "kahramanmaras_changed_part",
        ("kahramanmaras_changed_part.png",),
        "the buildings the changed-part option moves: pre | post orthos with the outline | cells flagged at 99 %",
        "bench/figures/kahramanmaras_changed_part.py",
        (
            _cmd(
                "{python} bench/eval_kahramanmaras.py --run "
                + KAHRA
                + " --modes region --calibrations auto --out {work}/kahramanmaras_changed_part/off"
            ),
            _cmd(
                "{python} bench/eval_kahramanmaras.py --run "
                + KAHRA
                + " --modes region --calibrations auto --changed-part on --out {work}/kahramanmaras_changed_part/on"
            ),
            _cmd(
                "{python} bench/figures/kahramanmaras_changed_part.py --run "
                + KAHRA
                + " --default {work}/kahramanmaras_changed_part/off/eval_building_damage_region.gpkg"
                " --option {work}/kahramanmaras_changed_part/on/eval_building_damage_region.gpkg"
                " --out {docs}/kahramanmaras_changed_part.png"
            ),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        needs=("kahramanmaras_orthos",),
        cost="long",
        minutes=1.2,
        measured=True,
    ),
    Entry(
        "kahramanmaras_false_alarms",
        ("kahramanmaras_false_alarms.png",),
        "cells flagged at 99 % outside every changed building, coloured by whether CARS's own two DSMs see a "
        "change there too",
        "bench/figures/kahramanmaras_false_alarms.py",
        (
            _cmd("{python} bench/bench_kahramanmaras_cars.py cars --work {work}/kahramanmaras_false_alarms/cars"),
            _cmd(
                "{python} bench/figures/kahramanmaras_false_alarms.py --run "
                + KAHRA
                + " --cars-work {work}/kahramanmaras_false_alarms/cars --png {docs}/kahramanmaras_false_alarms.png"
            ),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        tools=("cars",),
        needs=("kahramanmaras_orthos",),
        cost="long",
        minutes=30.0,
        note="CARS 1.3 in its own environment (docs/kahramanmaras.md, shared/notes/peers.md)",
    ),
    Entry(
        "mpp_kahramanmaras",
        ("mpp_kahramanmaras_current.png",),
        "geocd mpp's building and change layers on the Kahramanmaraş orthos and pair-DEMs",
        "bench/figures/mpp_show.py",
        (
            _cmd(
                "{geocd} mpp --image-a "
                + KAHRA
                + "/orthos/pre_event_img1.tif --image-b "
                + KAHRA
                + "/orthos/post_event_img1.tif --dsm-a "
                + KAHRA
                + "/stereo/pre_event/pre_event_img1__pre_event_img2.tif --dsm-b "
                + KAHRA
                + "/stereo/post_event/post_event_img1__post_event_img2.tif --ground "
                + KAHRA
                + "/sc_ground_model.tif --out {work}/mpp_kahramanmaras/mpp"
            ),
            _cmd(
                "{python} bench/figures/mpp_show.py kahra {work}/mpp_kahramanmaras/mpp "
                + KAHRA
                + " mpp_kahramanmaras_current"
            ),
        ),
        data=("cnes_picanteo_kahramanmaras",),
        needs=("kahramanmaras_orthos",),
        cost="long",
        minutes=4.6,
        measured=True,
    ),
    # ------------------------------------------------------------------ DEM differencing
    Entry(
        "demdiff",
        (
            "msh_26_27_dh.png",
            "msh_2_27_dh.png",
            "demdiff_error_model.png",
            "demdiff_demcompare_dh.png",
            "msh_timeseries.png",
        ),
        "Mount St Helens Δh maps (26 → 27, 2 → 27), the error model of 26 → 27, the demcompare control and the "
        "dome's volume series 2004–2007",
        "bench/bench_demdiff.py",
        (_cmd("{python} bench/bench_demdiff.py --figures {docs}"),),
        data=("usgs_msh_dome_dems", "cnes_demcompare_srtm"),
        minutes=1.4,
        measured=True,
    ),
    # ------------------------------------------------------------------ stereo and self-consistency
    Entry(
        "stereo_sample",
        ("stereo_sample_A_sat2__A_sat3.png", "stereo_sample_scores.png"),
        "sample_aoi pair-DEMs against the truth DSM: one pair's error and flags; bad matches per score decile",
        "bench/figures/stereo_show.py",
        (_cmd("{python} bench/figures/stereo_show.py sample"),),
        cost="long",
        minutes=5.0,
        measured=True,
        note="the page's tables and these two pictures were measured with surface_median 1 (docs/stereo.md says so); "
        "this command gives the default matcher's (median |z - truth| of A_sat1__A_sat2 0.08 m, the table's 0.15 m), "
        "so the committed pictures stay those of the tables until the page is re-measured",
    ),
    Entry(
        "stereo_s2p",
        ("stereo_s2p_pair_img_01__img_02.png",),
        "the Réunion Pléiades pair: geocd's DSM against s2p's",
        "bench/figures/stereo_show.py",
        (_cmd("{python} bench/figures/stereo_show.py s2p"),),
        data=("s2p_pleiades",),
        cost="long",
        minutes=20.0,
    ),
    Entry(
        "stereo_ventoux",
        ("stereo_ventoux.png",),
        "the Ventoux Pléiades pair: geocd's DSM against SRTM",
        "bench/figures/stereo_show.py",
        (_cmd("{python} bench/figures/stereo_show.py ventoux"),),
        data=("cnes_pleiades_ventoux",),
        cost="long",
        minutes=0.4,
        measured=True,
    ),
    Entry(
        "sc_marseille_scatter",
        ("sc_marseille_scatter.png",),
        "score × |Δ̃| with the significance curves learned on the Marseille Pléiades triplet's three pair-DEMs",
        "bench/eval_triplet_consistency.py",
        (
            _cmd("{python} bench/eval_triplet_consistency.py --write-manifest {work}/sc_marseille_scatter"),
            _cmd("{geocd} stereo {work}/sc_marseille_scatter --out {work}/sc_marseille_scatter/out"),
            _cmd(
                "{python} bench/eval_triplet_consistency.py {work}/sc_marseille_scatter/out/stereo "
                "--plot {docs}/sc_marseille_scatter.png"
            ),
        ),
        data=("s2p_pleiades",),
        cost="long",
        minutes=30.0,
    ),
    Entry(
        "bigstereo",
        ("bigstereo_quicklook.png",),
        "a crop of the generated 1 250² stereo scene: one view per epoch, the truth Δh and the change mask at 99 %",
        "bench/plot_big_stereo_scene.py",
        (
            _cmd(
                "{python} bench/make_big_stereo_scene.py {work}/bigstereo/calib1k --cells 1000 --seed 101 --views-a 3"
            ),
            _cmd("{python} bench/bench_big_stereo_change.py model {work}/bigstereo/calib1k {work}/bigstereo/model"),
            _cmd("{python} bench/make_big_stereo_scene.py {work}/bigstereo/st1250 --cells 1250"),
            _cmd(
                "{python} bench/bench_big_stereo_change.py run {work}/bigstereo/st1250 {work}/bigstereo/run1250 "
                "--model {work}/bigstereo/model/model.json --json {work}/bigstereo/run.1250.json"
            ),
            _cmd(
                "{python} bench/plot_big_stereo_scene.py {work}/bigstereo/st1250 {work}/bigstereo/run1250 "
                "{docs}/bigstereo_quicklook.png"
            ),
        ),
        cost="slow",
        minutes=120.0,
    ),
    # ------------------------------------------------------------------ other methods on sample_aoi
    Entry(
        "screen",
        ("screen_sample_aoi.png",),
        "the 2-D screen on sample_aoi: the two views, the dissimilarity, the change mask against truth",
        "bench/figures/screen_show.py",
        (
            _cmd("{geocd} screen sample_aoi --out {work}/screen/run"),
            _cmd("{python} bench/figures/screen_show.py {work}/screen/run"),
        ),
        minutes=0.3,
        measured=True,
    ),
    Entry(
        "ortho",
        ("ortho_sample_aoi.png",),
        "classic against true orthos of sample_aoi made on geocd stereo's DSMs",
        "bench/figures/ortho_show.py",
        (
            _cmd("{geocd} ortho sample_aoi --out {work}/ortho/run"),
            _cmd("{python} bench/figures/ortho_show.py {work}/ortho/run"),
        ),
        cost="long",
        minutes=2.6,
        measured=True,
    ),
    Entry(
        "probchange",
        ("probchange_sample_aoi.png", "probchange_sigma.png"),
        "probabilistic change on sample_aoi against MVS-then-subtract and the self-consistency test; σ and prior",
        "bench/figures/probchange_show.py",
        (
            _cmd(
                "{python} bench/figures/probchange_show.py --work {work}/probchange --scenes sample_aoi,sun_same,sun_other"
            ),
        ),
        cost="slow",
        minutes=90.0,
    ),
    Entry(
        "mpp_sample_aoi",
        ("mpp_sample_aoi.png", "mpp_edges_sample_aoi.png"),
        "geocd mpp's buildings of both dates and their changes on sample_aoi; the DSM's and the ortho's walls "
        "against the footprints",
        "bench/figures/mpp_show.py",
        (
            _cmd("{geocd} mpp sample_aoi --out {work}/mpp_sample_aoi/run"),
            _cmd("{python} bench/figures/mpp_show.py town sample_aoi {work}/mpp_sample_aoi/run --seeds 0 --only EH"),
            _cmd("{python} bench/figures/mpp_show.py edges sample_aoi {work}/mpp_sample_aoi/run"),
        ),
        cost="long",
        minutes=30.0,
    ),
    Entry(
        "mpp_levir",
        ("mpp_levir.png",),
        "the marked point process (ED, grey-image prototypes) on a LEVIR-CD pair",
        "bench/figures/mpp_show.py",
        (_cmd("{python} bench/figures/mpp_show.py levir"),),
        data=("levircd_building_change_samples",),
        env={"NUMBA_NUM_THREADS": "1"},
        cost="long",
        minutes=20.0,
    ),
    Entry(
        "landcover_show",
        ("landcover_pr.png", "landcover_views.png", "landcover_sample_maps.png"),
        "land-cover integration on sample_aoi: PR curves, F1 against the number of views, the maps",
        "bench/figures/landcover_show.py",
        (_cmd("{python} bench/figures/landcover_show.py --work {work}/landcover_show"),),
        cost="long",
        minutes=20.0,
    ),
    Entry(
        "landcover_cli",
        ("landcover_cli_ablation.png",),
        "the ablation report of `geocd landcover integrate` after the page's five commands (PR curves, AP per variant)",
        "geocd landcover (geocd/landcover/pipeline.py: pr_figure)",
        (
            _cmd(
                "{geocd} landcover train --labels examples/sample_aoi_vegetation_labels.gpkg --positive vegetation "
                "--image sample_aoi/images/A_air1.tif --image sample_aoi/images/A_air2.tif --manifest "
                "sample_aoi/scene.yaml --out {work}/landcover_cli/air.joblib"
            ),
            _cmd(
                "{geocd} landcover train --labels examples/sample_aoi_vegetation_labels.gpkg --positive vegetation "
                "--image sample_aoi/images/A_sat1.tif --manifest sample_aoi/scene.yaml "
                "--out {work}/landcover_cli/sat.joblib"
            ),
            _cmd(
                "{geocd} landcover predict --model {work}/landcover_cli/air.joblib --image "
                "sample_aoi/images/A_air2.tif --manifest sample_aoi/scene.yaml --posting 1 "
                "--out {work}/landcover_cli/air --prefix air"
            ),
            _cmd(
                "{geocd} landcover predict --model {work}/landcover_cli/sat.joblib --image "
                "sample_aoi/images/A_sat1.tif --manifest sample_aoi/scene.yaml --posting 1 "
                "--out {work}/landcover_cli/sat --prefix sat"
            ),
            _cmd(
                "{geocd} landcover integrate --detailed {work}/landcover_cli/air/air_ground.tif --coarse "
                "{work}/landcover_cli/sat/sat_ground.tif --manifest sample_aoi/scene.yaml --posting 1 --n-fit 300 "
                "--truth sample_aoi/truth/cover_A.tif --truth-values 1,2 --exclude-labels "
                "examples/sample_aoi_vegetation_labels.gpkg --class-name vegetation --out {work}/landcover_cli/gp"
            ),
            ("copy", "{work}/landcover_cli/gp/landcover_ablation.png", "{docs}/landcover_cli_ablation.png"),
        ),
        cost="long",
        minutes=3.7,
        measured=True,
    ),
    Entry(
        "landcover_baviaans",
        ("landcover_baviaans.png",),
        "vegetation over the Baviaans site from two aerial frames (2015) and the QuickBird-2 image (2003), "
        "integrated by the GP",
        "bench/figures/landcover_baviaans.py",
        (_cmd("{python} bench/figures/landcover_baviaans.py"),),
        data=("orthority_baviaans_aerial_qb2",),
        cost="long",
        minutes=2.0,
        measured=True,
    ),
    Entry(
        "volume",
        ("volume_roc.png", "volume_change_maps.png", "volume_height.png"),
        "the volumetric model on sample_aoi: ROC against Carlotto's baseline, change maps, the expected height",
        "geocd/volume/evaluate.py",
        (
            _cmd("{python} -m geocd.volume.evaluate sample_aoi --out {work}/volume/out --work {work}/volume/work"),
            *(
                ("copy", f"{{work}}/volume/out/{p}", f"{{docs}}/{p}")
                for p in ("volume_roc.png", "volume_change_maps.png", "volume_height.png")
            ),
        ),
        cost="slow",
        minutes=120.0,
    ),
    # ------------------------------------------------------------------ tables (no picture)
    Entry(
        "peers",
        (),
        "the README's table of results against peers: geocd and CARS, xDEM, GDAL measured in turn in one run "
        "(CPU seconds, ratio, goal, accuracy beside)",
        "bench/peers/__main__.py",
        (_cmd("{python} -m bench.peers --install --repeat 3 --work {work}/peers --readme"),),
        data=("s2p_pleiades", "usgs_msh_dome_dems"),
        tables=("README.md 'Results on real data', from bench/results/peers.json",),
        cost="long",
        minutes=38.0,
        note="CARS 1.3 and xDEM are installed once (pip) in venvs of their own under ~/.cache/geocd/peers "
        "($GEOCD_PEERS); a peer that cannot be installed or run leaves its rows with the reason, no figure",
    ),
)


def by_name() -> dict[str, Entry]:
    """{name: entry}."""
    return {e.name: e for e in ENTRIES}


def pictures() -> dict[str, Entry]:
    """{picture file name: the entry that writes it}."""
    return {p: e for e in ENTRIES for p in e.pictures}
