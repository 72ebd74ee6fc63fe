"""Runs inside the real QGIS desktop (``qgis --code desktop_driver.py``) for test_desktop.py.

It does what an analyst does, one scenario after another: loads the input layers into the
project, opens an algorithm's own dialog (``processing.createAlgorithmDialog``), fills the
fields a user must fill through the dialog's widget wrappers (and types into, then clears,
the optional text fields where the scenario says so, with real key presses), presses Run,
presses Cancel where asked, waits, and records from inside QGIS what the user would see:
message boxes, the dialog's log, the progress bar, the layers the run added to the project
with their renderers, legends and the data's range, and a screenshot of the main window.

The plan comes from ``SLIPMAP_DESKTOP_PLAN`` (JSON written by the test); the record goes to
the plan's ``out`` file after every scenario, so a crash still leaves what happened before.
No assertion is made here: the test reads the record. Nothing here is SlipMap code: only
QGIS's own API, as the desktop uses it.
"""

import json
import math
import os
import time
import traceback

from qgis.core import (
    QgsApplication,
    QgsCategorizedSymbolRenderer,
    QgsGraduatedSymbolRenderer,
    QgsMapLayerType,
    QgsProject,
    QgsRasterLayer,
    QgsRectangle,
    QgsRuleBasedRenderer,
    QgsSingleBandPseudoColorRenderer,
    QgsVectorLayer,
)
from qgis.PyQt.QtCore import Qt, QTimer
from qgis.PyQt.QtTest import QTest
from qgis.PyQt.QtWidgets import (
    QApplication,
    QLineEdit,
    QMessageBox,
    QProgressBar,
    QTextEdit,
)
from qgis.utils import iface

with open(os.environ["SLIPMAP_DESKTOP_PLAN"], encoding="utf-8") as _f:
    PLAN = json.load(_f)
RECORD = {"scenarios": [], "started": time.time()}


def save():
    tmp = PLAN["out"] + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(RECORD, f, indent=1, default=str)
    os.replace(tmp, PLAN["out"])


def later(ms, fn):
    QTimer.singleShot(int(ms), fn)


# --------------------------------------------------------------------------- what QGIS shows


def _finite(v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def fingerprint(layer):
    """What a renderer looks like, structurally: its type, the symbol layers' types, how many
    data-defined properties and whether labels are on (colours left out: QGIS's default
    symbol has a random colour)."""
    if layer.type() == QgsMapLayerType.RasterLayer:
        r = layer.renderer()
        return {"renderer": r.type() if r else None}
    r = layer.renderer()
    symbols = []
    if r is not None:
        from qgis.core import QgsRenderContext

        for s in r.symbols(QgsRenderContext()):
            for i in range(s.symbolLayerCount()):
                sl = s.symbolLayer(i)
                dd = sl.dataDefinedProperties()
                n = sum(1 for k in dd.propertyKeys() if dd.property(k).isActive())
                symbols.append([sl.layerType(), n])
    return {
        "renderer": r.type() if r else None,
        "symbols": sorted(symbols),
        "labels": bool(layer.labelsEnabled()),
    }


def default_fingerprint(layer):
    """The fingerprint QGIS gives the same data source with no style at all."""
    if layer.type() == QgsMapLayerType.RasterLayer:
        plain = QgsRasterLayer(layer.source(), "plain", layer.providerType())
    else:
        plain = QgsVectorLayer(
            layer.source(), "plain", layer.providerType(), QgsVectorLayer.LayerOptions(False)
        )
    if not plain.isValid():
        return None
    if plain.type() == QgsMapLayerType.RasterLayer:
        # a raster's default is not loaded from a sidecar here: QgsRasterLayer reads a .qml
        # sidecar as its default style only through loadDefaultStyle, which the ctor calls;
        # compare with the renderer GDAL's band count gives (gray for one band)
        return {"renderer": "singlebandgray" if plain.bandCount() == 1 else "multibandcolor"}
    return fingerprint(plain)


def legend_and_data(layer):
    """The legend's classes and the range of the values they classify."""
    out = {}
    if layer.type() == QgsMapLayerType.RasterLayer:
        r = layer.renderer()
        out["bands"] = layer.bandCount()
        if isinstance(r, QgsSingleBandPseudoColorRenderer):
            band = r.band() if hasattr(r, "band") else r.inputBand()
            out["band"] = band
            out["class_min"] = _finite(r.classificationMin())
            out["class_max"] = _finite(r.classificationMax())
            shader = r.shader().rasterShaderFunction()
            out["labels"] = [it.label for it in shader.colorRampItemList()]
            stats = layer.dataProvider().bandStatistics(band)
            out["data_min"] = _finite(stats.minimumValue)
            out["data_max"] = _finite(stats.maximumValue)
        out["legend"] = (
            [t for t, _ in layer.legendSymbologyItems()]
            if hasattr(layer, "legendSymbologyItems")
            else []
        )
        return out
    r = layer.renderer()
    out["features"] = layer.featureCount()
    out["fields"] = [f.name() for f in layer.fields()]
    for name in ("right_lateral", "dz"):  # the signed values a reader reads off the map
        if name in out["fields"]:
            values = _expression_values(layer, f'"{name}"')
            out[f"{name}_range"] = [min(values), max(values)] if values else None
    if isinstance(r, QgsGraduatedSymbolRenderer):
        out["attribute"] = r.classAttribute()
        out["ranges"] = [[rg.lowerValue(), rg.upperValue(), rg.label()] for rg in r.ranges()]
        values = _expression_values(layer, r.classAttribute())
        out["data_min"] = min(values) if values else None
        out["data_max"] = max(values) if values else None
    elif isinstance(r, QgsCategorizedSymbolRenderer):
        out["attribute"] = r.classAttribute()
        out["categories"] = [[str(c.value()), c.label()] for c in r.categories()]
        values = _expression_values(layer, r.classAttribute(), numeric=False)
        out["data_values"] = sorted({str(v) for v in values})
    elif isinstance(r, QgsRuleBasedRenderer):
        out["rules"] = [c.label() for c in r.rootRule().children()]
    return out


def _expression_values(layer, expression, numeric=True):
    from qgis.core import QgsExpression, QgsExpressionContext, QgsExpressionContextUtils

    exp = QgsExpression(expression)
    ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    exp.prepare(ctx)
    values = []
    for f in layer.getFeatures():
        ctx.setFeature(f)
        v = exp.evaluate(ctx)
        if numeric:
            v = _finite(v)
            if v is not None:
                values.append(v)
        elif v is not None:
            values.append(v)
    return values


def layer_record(layer, root):
    node = root.findLayer(layer.id())
    order = [n.layerId() for n in root.findLayers()]
    return {
        "name": layer.name(),
        "id": layer.id(),
        "source": layer.source(),
        "kind": "raster" if layer.type() == QgsMapLayerType.RasterLayer else "vector",
        "valid": layer.isValid(),
        "fingerprint": fingerprint(layer),
        "default_fingerprint": default_fingerprint(layer),
        "opacity": layer.opacity() if hasattr(layer, "opacity") else None,
        "tree_index": order.index(layer.id()) if node is not None else None,
        **legend_and_data(layer),
    }


# --------------------------------------------------------------------------- one scenario


class Scenario:
    def __init__(self, plan, done):
        self.plan, self.done = plan, done
        self.rec = {"id": plan["id"], "alg": plan["alg"], "message_boxes": [], "events": []}
        self.dlg = None
        self.t0 = time.time()
        self.input_layers = set()

    # ---- helpers
    def event(self, text):
        self.rec["events"].append([round(time.time() - self.t0, 2), text])
        RECORD["current"] = self.rec  # what was done, should the desktop die before the end
        save()

    def log_text(self):
        box = self.dlg.findChild(QTextEdit, "txtLog") if self.dlg is not None else None
        return box.toPlainText() if box is not None else ""

    def progress(self):
        bar = self.dlg.findChild(QProgressBar, "progressBar") if self.dlg is not None else None
        return bar.value() if bar is not None else None

    def close_message_boxes(self):
        w = QApplication.activeModalWidget()
        while isinstance(w, QMessageBox):
            self.rec["message_boxes"].append([w.windowTitle(), w.text()])
            self.event(f"message box: {w.windowTitle()}: {w.text()[:200]}")
            w.done(QMessageBox.No if w.standardButtons() & QMessageBox.No else 0)
            QApplication.processEvents()
            w = QApplication.activeModalWidget()

    # ---- steps
    def start(self):
        try:
            project = QgsProject.instance()
            project.clear()  # a new project: its CRS becomes the first layer's
            for name, path in self.plan.get("layers", {}).items():
                layer = QgsVectorLayer(path, name, "ogr")
                project.addMapLayer(layer)
                self.input_layers.add(layer.id())
                self.event(f"layer {name} valid={layer.isValid()}")
            from qgis import processing

            self.event("opening the dialog")
            self.dlg = processing.createAlgorithmDialog(self.plan["alg"])
            if self.dlg is None:
                self.rec["error"] = "createAlgorithmDialog returned None"
                return self.finish()
            self.dlg.resize(1100, 820)
            self.dlg.show()
            self.event("dialog shown")
            later(800, self.fill)
        except Exception:  # noqa: BLE001 - recorded for the test
            self.rec["error"] = traceback.format_exc()
            self.finish()

    def wrapper(self, name):
        return self.dlg.mainWidget().wrappers[name]

    def fill(self):
        try:
            panel = self.dlg.mainWidget()
            ctx = panel.processing_context
            project = QgsProject.instance()
            for name, value in self.plan.get("values", {}).items():
                if name not in self.dlg.mainWidget().wrappers:
                    self.event(f"the dialog has no field {name}")
                    continue
                if isinstance(value, dict) and "layer" in value:
                    value = project.mapLayersByName(value["layer"])[0]
                self.wrapper(name).setParameterValue(value, ctx)
            for name, value in self.plan.get("outputs", {}).items():
                self.wrapper(name).setParameterValue(value, ctx)
            for name in self.plan.get("clear", []):
                self.type_and_clear(name)
            self.event("fields filled")
            self.rec["parameters"] = {
                k: repr(v) for k, v in self.dlg.createProcessingParameters().items()
            }
            if self.plan.get("shot_dialog"):
                self.dlg.grab().save(self.plan["shot_dialog"])
            later(300, self.run)
        except Exception:  # noqa: BLE001
            self.rec["error"] = traceback.format_exc()
            self.finish()

    def type_and_clear(self, name):
        """Type a character into each text box of the parameter's widget, then delete it, with
        key presses: the field is empty again, as after a user changed their mind."""
        widget = self.wrapper(name).wrappedWidget()
        edits = [widget] if isinstance(widget, QLineEdit) else widget.findChildren(QLineEdit)
        if not edits:
            self.event(f"{name}: no text box to clear")
        for edit in edits:
            if not edit.isEnabled() or edit.isReadOnly():
                continue
            edit.setFocus()
            QTest.keyClicks(edit, "a")
            QTest.keyClick(edit, Qt.Key_End)
            QTest.keyClick(edit, Qt.Key_Backspace)
            edit.editingFinished.emit()
        self.event(f"{name}: typed and cleared")

    def run(self):
        self.t_run = time.time()
        self.progress_seen = []
        self.cancel_pressed = False
        # a check that fails shows a modal QMessageBox inside click(): a timer closes it
        self.watch = QTimer()
        self.watch.timeout.connect(self.close_message_boxes)
        self.watch.start(250)
        self.event("Run pressed")
        self.dlg.runButton().click()
        later(300, self.wait)

    def wait(self):
        try:
            self.close_message_boxes()
            log = self.log_text()
            p = self.progress()
            if not self.progress_seen or self.progress_seen[-1][1] != p:
                last = log.strip().splitlines()[-1] if log.strip() else ""
                self.progress_seen.append([round(time.time() - self.t_run, 2), p, last[:160]])
            cancel_at = self.plan.get("cancel_at_progress")
            if cancel_at is not None and not self.cancel_pressed and (p or 0) >= cancel_at:
                self.cancel_pressed = True
                self.event(f"Cancel pressed at {p} %")
                self.dlg.cancelButton().click()
            ended = "Execution completed in" in log or "Execution failed after" in log
            refused = self.rec["message_boxes"] and "Algorithm started at" not in log
            if ended or refused or time.time() - self.t_run > self.plan.get("timeout_s", 240):
                self.rec["timed_out"] = not (ended or refused)
                later(1500, self.collect)
            else:
                later(200, self.wait)
        except Exception:  # noqa: BLE001
            self.rec["error"] = traceback.format_exc()
            self.finish()

    def collect(self):
        try:
            self.watch.stop()
            self.close_message_boxes()
            self.rec["log"] = self.log_text()
            self.rec["progress"] = self.progress_seen
            self.rec["completed"] = "Execution completed in" in self.rec["log"]
            self.rec["results"] = {k: repr(v) for k, v in (self.dlg.results() or {}).items()}
            self.rec["message_bar"] = (
                [it.text() for it in self.dlg.messageBar().items()]
                if hasattr(self.dlg.messageBar(), "items")
                else []
            )
            project = QgsProject.instance()
            root = project.layerTreeRoot()
            self.rec["layers"] = [
                layer_record(layer, root)
                for layer in project.mapLayers().values()
                if layer.id() not in self.input_layers
            ]
            self.rec["seconds"] = round(time.time() - self.t_run, 1)
            if self.plan.get("shot") and self.rec["layers"]:
                outputs = [x for x in project.mapLayers().values() if x.crs().isValid()]
                if outputs:  # north up in the data's own CRS, as an analyst's project is
                    project.setCrs(outputs[0].crs())
                canvas = iface.mapCanvas()
                extent = QgsRectangle()
                extent.setMinimal()
                for layer in project.mapLayers().values():
                    if layer.id() not in self.input_layers or not self.rec["layers"]:
                        extent.combineExtentWith(
                            canvas.mapSettings().layerExtentToOutputExtent(layer, layer.extent())
                        )
                canvas.setExtent(extent.buffered(extent.width() * 0.05))
                canvas.refresh()
                later(2500, self.shoot)
            else:
                self.finish()
        except Exception:  # noqa: BLE001
            self.rec["error"] = traceback.format_exc()
            self.finish()

    def shoot(self):
        try:
            iface.mainWindow().grab().save(self.plan["shot"])
            self.rec["shot"] = self.plan["shot"]
        except Exception:  # noqa: BLE001
            self.rec["shot_error"] = traceback.format_exc()
        self.finish()

    def finish(self):
        RECORD["scenarios"].append(self.rec)
        RECORD.pop("current", None)
        save()
        try:
            if self.dlg is not None:
                # hidden, not closed: QGIS 3.40's dialog deletes itself on close, and the
                # Python wrapper's own delete would then crash QGIS; kept to the end instead
                self.dlg.hide()
                DIALOGS.append(self.dlg)
        except Exception:  # noqa: BLE001
            pass
        later(500, self.done)


# --------------------------------------------------------------------------- the plugin state


def provider_record():
    reg = QgsApplication.processingRegistry()
    provider = reg.providerById("slipmap")
    out = {"provider": provider is not None}
    if provider is None:
        return out
    out["provider_active"] = provider.isActive()
    out["provider_warning"] = provider.warningMessage()
    out["long_name"] = provider.longName()
    algs = []
    for alg in provider.algorithms():
        ok, why = alg.canExecute()
        algs.append(
            {
                "id": alg.id(),
                "can_execute": ok,
                "why": why,
                "short_description": alg.shortDescription(),
                "flags": int(alg.flags()),
            }
        )
    out["algorithms"] = algs
    import qgis.utils

    out["plugin_loaded"] = "slipmap" in qgis.utils.plugins
    bar = iface.messageBar() if iface is not None else None
    out["message_bar"] = [it.text() for it in bar.items()] if bar is not None else []
    return out


def _text_of(widget):
    """The words a dialog shows: its title and every label and text box in it."""
    from qgis.PyQt.QtWidgets import QLabel

    parts = [widget.windowTitle()]
    parts += [w.text() for w in widget.findChildren(QLabel) if w.text()]
    parts += [w.toPlainText() for w in widget.findChildren(QTextEdit) if w.toPlainText()]
    return "\n".join(parts)


def watchdog():
    """Close any modal dialog a scenario does not expect (a Python error, a plugin's load
    error), recording its words, so the desktop never waits for a click that will not come."""
    w = QApplication.activeModalWidget()
    if w is not None and not isinstance(w, QMessageBox):
        RECORD.setdefault("unexpected_dialogs", []).append(_text_of(w)[:4000])
        save()
        w.close()


def main():
    from processing.core.ProcessingConfig import ProcessingConfig

    ProcessingConfig.setSettingValue(ProcessingConfig.KEEP_DIALOG_OPEN, True)
    RECORD["qgis_version"] = __import__("qgis.core", fromlist=["Qgis"]).Qgis.QGIS_VERSION
    try:
        RECORD["state"] = provider_record()
    except Exception:  # noqa: BLE001 - recorded for the test
        RECORD["state"] = {"provider": None, "error": traceback.format_exc()}
    save()
    scenarios = iter(PLAN["scenarios"])

    def step():
        try:
            plan = next(scenarios)
        except StopIteration:
            try:
                RECORD["state_end"] = provider_record()
            except Exception:  # noqa: BLE001
                RECORD["state_end"] = {"error": traceback.format_exc()}
            RECORD["finished"] = True
            save()
            os._exit(0)  # QGIS 3.22 may abort on a scripted exit; everything is saved
        # PyQt holds a timer's bound method weakly: keep the scenario alive while it runs
        ALIVE[:] = [Scenario(plan, done=step)]
        ALIVE[0].start()

    window = iface.mainWindow()
    window.resize(1600, 1000)
    window.showMaximized()
    step()


ALIVE = []
DIALOGS = []


WATCHDOG = QTimer()
WATCHDOG.timeout.connect(watchdog)
WATCHDOG.start(1000)
later(PLAN.get("start_delay_ms", 2500), main)
