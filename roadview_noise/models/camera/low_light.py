"""Low light: the scene under a lower illuminance, seen by an auto-exposing sensor (models.md §2.8; D3.5 CNF13–15,
Eq. 1)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...param_checks import rgb
from ...physics.cfa import SiteLayout
from ...physics.photometry import SAMPLE_STEP_PX
from ...physics.sensor_noise import SHOT_NOISE, SensorSettings, expose
from ...registry import register
from ...types import RawFrame

BACKENDS = ("physical", "onnx")


@register
@dataclass(frozen=True)
class LowLightCamera(Model):
    """Dusk/night illumination before the weather (D3.5 Eq. 1; models.md §2.8).

    ``physical`` (default; :mod:`roadview_noise.physics.sensor_noise`): the frame is linear radiance already (the
    readers undo the sRGB curve; ``white_balance_gains`` undoes the ISP's white balance), scaled by the illuminance
    ratio ``k = illuminance_lux / reference_illuminance_lux``; the auto-exposure restores brightness with a gain
    ``g = min(max_gain, 1/k)`` (longer exposure × analogue gain, capped); the sensor collects ``k·x·full_well_e``
    electrons, adds shot, dark-current and read noise, amplifies by g and digitises with an ``adc_bits`` ADC; the
    result is re-processed (white balance redone; the writer re-applies the sRGB curve). Mean output = k·g × input.
    Raw Bayer mosaics run natively: every site through the same sensor model, no demosaic, digitised by the ADC
    whose codes the file holds (its black and white level; ``adc_bits`` and ``adc_black_level_dn`` describe the
    notional ADC of an RGB frame), not by a second one. Identity: ``illuminance_lux = reference_illuminance_lux``,
    ``read_noise_e = dark_current_e_per_s = 0``, ``shot_noise: off`` give a raw mosaic's DN back exactly (codes below
    black included) and an RGB frame within the ADC's step (``adc_bits: 16``: the 8-bit codes exactly).

    ``onnx``: a user-supplied image-to-image generator (e.g. a CycleGAN day→night generator exported to ONNX,
    :mod:`roadview_noise.io.onnx_image`) at full resolution (padded to ``onnx_input_multiple_px``, never cropped to
    256×256); RGB frames only. The luminance factor is then measured (output/input mean radiance).

    Coupling (D3.5: "the luminosity parameter of the weather models is lowered accordingly"): the factor applied
    (k·g, or the measured one) multiplies ``conditions.luminance_factor``. Weather models after this step estimate
    airlight and particle radiance from the darkened frame, which already carries the factor once, and scale
    radiances given in absolute (daylight) terms by it — no double darkening. Sensor noise is added here, before
    the weather (D3.5's order; its CycleGAN also produced noisy night images): weather radiance added later is
    noise-free, so dense fog looks smoother than a real night fog. Diagnostics: ratio, gain, luminance factor,
    mean photo-electrons and SNR at the frame's mean signal."""

    id: ClassVar[str] = "low_light.camera"
    stage: ClassVar[Stage] = Stage.SCENE
    sensor: ClassVar[str] = "camera"
    summary: ClassVar[str] = "low light: illuminance ratio, capped auto-exposure gain, shot/read/dark noise, ADC"

    backend: str = param("physical", choices=BACKENDS, doc="physical sensor model, or onnx (user-supplied generator)")
    illuminance_lux: float = param(10.0, unit="lx", gt=0, doc="scene illuminance (street lighting ≈ 10 lx)")
    reference_illuminance_lux: float = param(10000.0, unit="lx", gt=0, doc="illuminance of the input (overcast "
                                                                           "day ≈ 10 000 lx)")
    max_gain: float = param(8.0, unit="1", ge=1, le=1e4, doc="auto-exposure gain cap (exposure × analogue gain)")
    full_well_e: float = param(10000.0, unit="e⁻", gt=0, doc="electrons of a full-scale input value")
    read_noise_e: float = param(3.0, unit="e⁻", ge=0, doc="read noise, standard deviation (input-referred)")
    dark_current_e_per_s: float = param(5.0, unit="e⁻/s", ge=0, doc="dark current (over the profile's exposure)")
    shot_noise: str = param("gaussian", choices=SHOT_NOISE, doc="gaussian of exact variance (fast), poisson "
                                                                "(exact, slower) or off")
    adc_bits: int = param(12, unit="bit", ge=8, le=16, doc="ADC resolution (RGB frames; a raw mosaic keeps its own)")
    adc_black_level_dn: float = param(64.0, unit="DN", ge=0, doc="ADC black offset (keeps negative noise; RGB frames, "
                                                                 "a raw mosaic keeps its own black level)")
    white_balance_gains: Any = param((1.0, 1.0, 1.0), unit="1", doc="[R, G, B] white balance of the input's ISP "
                                                                   "(undone before the sensor, RGB only)")
    onnx_model: Any = param(None, unit="path", doc="onnx: the generator's .onnx file")
    onnx_input_multiple_px: int = param(4, unit="px", ge=1, le=1024, doc="onnx: pad height and width to a "
                                                                          "multiple of this")
    onnx_threads: int = param(1, unit="1", ge=1, le=256, doc="onnx: onnxruntime threads per worker")

    def validate(self) -> None:
        object.__setattr__(self, "white_balance_gains",
                           rgb(self.white_balance_gains, self.id, "white_balance_gains", low=0.0, low_open=True))
        if self.adc_black_level_dn >= (1 << self.adc_bits) - 1:
            raise ModelError(f"must be below the ADC full scale {(1 << self.adc_bits) - 1}", model=self.id,
                             field="adc_black_level_dn")
        if self.backend == "onnx" and not isinstance(self.onnx_model, str):
            raise ModelError("the onnx back-end needs onnx_model: the path of an .onnx file", model=self.id,
                             field="onnx_model")

    def settings(self, exposure_time_s: float, raw: RawFrame | None = None) -> SensorSettings:
        """The sensor of one frame; a raw mosaic's ADC is the one its DN came from (black to white level)."""
        k = self.illuminance_lux / self.reference_illuminance_lux
        top, black = ((raw.white_level_dn, raw.black_level_dn) if raw is not None else
                      ((1 << self.adc_bits) - 1, self.adc_black_level_dn))
        return SensorSettings(illuminance_ratio=k, gain=min(self.max_gain, 1.0 / k), full_well_e=self.full_well_e,
                              read_noise_e=self.read_noise_e, dark_e=self.dark_current_e_per_s * exposure_time_s,
                              adc_max_dn=float(top), adc_black_dn=float(black))

    def apply(self, data, *, state, drawn, rng):
        signal = data.signal()
        layout = SiteLayout.of(data)
        mean_in = np.array([s.mean(dtype=np.float64) for s in layout.channel_samples(signal, step=SAMPLE_STEP_PX)])
        if self.backend == "onnx":
            if isinstance(data, RawFrame):
                raise ModelError("the onnx back-end translates RGB images; a raw Bayer mosaic needs the physical "
                                 "back-end", model=self.id, field="backend")
            from ...io.onnx_image import run_image_network

            out = run_image_network(signal, self.onnx_model, multiple_px=self.onnx_input_multiple_px,
                                    threads=self.onnx_threads)
            mean_out = np.array([s.mean(dtype=np.float64) for s in layout.channel_samples(out, step=SAMPLE_STEP_PX)])
            factor = float(mean_out.sum() / mean_in.sum()) if mean_in.sum() > 0 else 1.0
            diagnostics = {"luminance_factor": factor}
        else:
            s = self.settings(data.profile.exposure_time_s, data if isinstance(data, RawFrame) else None)
            out = expose(signal, s, rng, shot_noise=self.shot_noise, white_balance=self.white_balance_gains)
            factor = s.luminance_factor
            electrons = s.illuminance_ratio * s.full_well_e * float(mean_in.mean())
            noise_e = float(np.sqrt((electrons if self.shot_noise != "off" else 0.0) + s.read_noise_e ** 2 + s.dark_e))
            diagnostics = {"illuminance_ratio": s.illuminance_ratio, "gain": s.gain, "luminance_factor": factor,
                           "mean_electrons": electrons,
                           "snr_at_mean": electrons / noise_e if noise_e > 0 else None}
        conditions = dataclasses.replace(data.conditions,
                                         luminance_factor=data.conditions.luminance_factor * factor)
        return dataclasses.replace(data.with_signal(out), conditions=conditions), diagnostics
