"""Update callbacks of ``camera.tof`` and ``material.tof``: what a changed setting sets off.

==============================  ================================================================================
callback                        on
==============================  ================================================================================
:func:`cameras_changed`         settings that move the LEDs or change the intrinsics: the cameras using the
                                data follow (:func:`.operators.apply_settings_to_cameras`), the preview restarts
:func:`fill_resolution`         ``use_resolution``: starts from the preset's resolution, then as above
:func:`fill_range`              ``use_range_m``: starts from the preset's range, then restarts the preview
:func:`settings_changed`        any other sensor or quality setting: restarts the live preview, if on
:func:`live_preview_toggled`    ``live_preview``: starts or stops the live preview
:func:`material_changed`        a ``material.tof`` setting: restarts the live preview, if on
==============================  ================================================================================

The property groups (:mod:`.properties`) import this module; it imports
:mod:`.operators` (camera sync, the live preview) and :mod:`.sensors`, neither of
which imports the property groups, so the add-on's imports form no circle.
"""

from __future__ import annotations

from . import operators, sensors


def cameras_changed(self, context) -> None:
    """A setting that moves the LEDs or changes the intrinsics: update the cameras using this data."""
    operators.apply_settings_to_cameras(self.id_data, context.scene if context else None)
    operators.settings_changed(self.id_data)


def fill_resolution(self, context) -> None:
    """Turning the override on starts from the preset's resolution."""
    if self.use_resolution:
        camera = sensors.preset_sensor(self)
        if camera is not None:
            self.width, self.height = camera.camera.width, camera.camera.height
    cameras_changed(self, context)


def fill_range(self, context) -> None:
    """Turning the override on starts from the preset's range."""
    if self.use_range_m:
        sensor = sensors.preset_sensor(self)
        if sensor is not None:
            self.range_m = sensor.range_m
    settings_changed(self, context)


def settings_changed(self, context) -> None:
    """Any other sensor or quality setting: restart the live preview, if on."""
    operators.settings_changed(self.id_data)


def live_preview_toggled(self, context) -> None:
    """``live_preview``: install or remove the preview handler, start or stop the preview."""
    operators.live_preview_toggled(self.id_data, self.live_preview)


def material_changed(self, context) -> None:
    """A near-IR material setting: restart the live preview of any camera, if on."""
    operators.settings_changed(None)
