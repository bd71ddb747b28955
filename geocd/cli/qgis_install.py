"""Install a QGIS plugin from a plugin repository (``plugins.xml``) headless, with QGIS's own installer.

This file runs under the Python that has PyQGIS (e.g. Debian's ``/usr/bin/python3`` with ``python3-qgis``),
never inside geocd's environment: ``geocd plugin-install`` starts it as a child process. It uses only the
standard library and QGIS, and does what Plugins ▸ Manage and Install Plugins ▸ Settings ▸ Add repository,
then ▸ Install does in the GUI:

1. registers the repository URL in the profile's settings and fetches its XML with QGIS's
   ``pyplugin_installer`` (same parser, same compatibility checks as the dialog);
2. downloads the plugin's zip from its ``download_url`` and unpacks it into the profile's
   ``python/plugins`` with QGIS's installing dialog (offscreen);
3. enables the plugin in the profile (``[PythonPlugins] <id>=true``), as the GUI does after installing.

The profile is QGIS's default one, or the one ``QGIS_CUSTOM_CONFIG_PATH`` names. One JSON line on stdout
reports the result; the exit code is 0 on success.

Usage: ``python3 qgis_install.py REPOSITORY_URL PLUGIN_ID [REPOSITORY_NAME]``
"""

from __future__ import annotations

import json
import os
import sys
import time


def _report(**kw) -> None:
    sys.stdout.write(json.dumps(kw) + "\n")
    sys.stdout.flush()


def install(url: str, plugin_id: str, repo_name: str = "geocd", timeout_s: float = 120.0) -> dict:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from qgis.core import QgsApplication, QgsSettings
    from qgis.PyQt.QtCore import QCoreApplication

    # the names QGIS itself runs under: its settings are <profile>/QGIS/QGIS3.ini
    QCoreApplication.setOrganizationName("QGIS")
    QCoreApplication.setOrganizationDomain("qgis.org")
    QCoreApplication.setApplicationName("QGIS3")
    QgsApplication.setPrefixPath(os.environ.get("QGIS_PREFIX_PATH", "/usr"), True)
    app = QgsApplication([], True)
    app.initQgis()
    python_dir = os.path.join(QgsApplication.pkgDataPath(), "python")  # pyplugin_installer lives there
    if python_dir not in sys.path:
        sys.path.append(python_dir)
    import qgis.utils

    settings_dir = QgsApplication.qgisSettingsDirPath()
    plugin_dir = os.path.join(settings_dir, "python", "plugins")
    os.makedirs(plugin_dir, exist_ok=True)
    # what QGIS's Python start-up sets in a GUI session
    qgis.utils.home_plugin_path = plugin_dir
    if plugin_dir not in qgis.utils.plugin_paths:
        qgis.utils.plugin_paths.append(plugin_dir)
    if plugin_dir not in sys.path:
        sys.path.insert(0, plugin_dir)

    from pyplugin_installer.installer_data import Repositories, plugins, repositories, reposGroup
    from pyplugin_installer.qgsplugininstallerinstallingdialog import QgsPluginInstallerInstallingDialog

    s = QgsSettings()
    s.setValue(f"{reposGroup}/{repo_name}/url", url)
    s.setValue(f"{reposGroup}/{repo_name}/enabled", True)
    s.sync()
    repositories.load()
    repositories.requestFetching(repo_name)
    t0 = time.monotonic()
    while repositories.all()[repo_name]["state"] == Repositories.STATE_LOADING:
        QCoreApplication.processEvents()
        time.sleep(0.02)
        if time.monotonic() - t0 > timeout_s:
            return {"ok": False, "error": f"fetching {url} timed out after {timeout_s:g} s"}
    rep = repositories.all()[repo_name]
    if rep["state"] != Repositories.STATE_LOADED:
        return {"ok": False, "error": f"cannot read the plugin repository {url}: {rep.get('error') or 'unavailable'}"}
    # the repository's own entry (the plugin manager's list hides experimental plugins unless the user ticks
    # "Show also experimental plugins"; installing it explicitly is what that tick allows)
    offered = {p["id"]: p for p in plugins.repoCache.get(repo_name, [])}
    plugin = offered.get(plugin_id)
    if plugin is None:
        return {
            "ok": False,
            "error": f"the repository {url} does not offer a plugin {plugin_id!r} compatible with "
            f"this QGIS (it offers {sorted(offered)})",
        }
    stable = not plugin.get("experimental")
    dlg = QgsPluginInstallerInstallingDialog(None, plugin, stable=stable)
    dlg.exec_()
    if dlg.result():
        return {"ok": False, "error": f"QGIS could not install {plugin_id}: {dlg.result()}"}
    installed = os.path.join(plugin_dir, plugin_id)
    if not os.path.isfile(os.path.join(installed, "metadata.txt")):
        return {"ok": False, "error": f"the zip did not unpack into {installed} (wrong top folder in the zip?)"}
    s.setValue(f"PythonPlugins/{plugin_id}", True)
    s.sync()
    version = plugin.get("version_available")
    experimental = bool(plugin.get("experimental"))
    app.exitQgis()
    return {
        "ok": True,
        "plugin": plugin_id,
        "version": version,
        "path": installed,
        "profile": settings_dir,
        "repository": url,
        "experimental": experimental,
    }


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        sys.stderr.write(__doc__ or "")
        return 2
    try:
        res = install(argv[0], argv[1], *(argv[2:3]))
    except ImportError as exc:
        res = {
            "ok": False,
            "error": f"PyQGIS is not importable by {sys.executable} ({exc}); install QGIS's Python "
            "bindings (Debian: apt-get install python3-qgis) or pass --qgis-python",
        }
    _report(**res)
    return 0 if res.get("ok") else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
