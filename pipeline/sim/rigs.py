"""A family of estimator designs other labs could have built (`simulate.rig`, docs/physics.md §11).

The built-in simulator is one rig among many: a setting that wins only on it is tuned to it. Each
member here changes what a lab building the estimator from its own parts would change: the read-out
circuit (divider values, supply, which side the FSR sits on, an op-amp front end), the FSR (another
conductance law, more part-to-part spread) and the silicone (preload, creep). Sample rates are
`simulate.fsr_rate_hz` / `ref_rate_hz`. `default` is the rig of docs/physics.md §1-10, unchanged.

Every figure is in docs/physics.md §11 with its source; none was chosen by how a model scores on it.
"""

from __future__ import annotations

from needlecue_runtime.frontend import Circuit, Divider, Transimpedance
from pipeline.sim.physics import Estimator

DEFAULT = "default"

RIGS: dict[str, Estimator] = {
    # The paper's estimator as docs/physics.md §4-6 describes it: 5 V divider, 10 kOhm, Uno ADC.
    DEFAULT: Estimator(),
    # A 3.3 V board (12-bit ADC over 3.3 V) with the FSR between output and ground and a 47 kOhm
    # fixed resistor: the output falls as the load grows.
    "divider-3v3-ground": Estimator(
        front_end=Divider(circuit="divider", supply_v=3.3, fixed_kohm=47.0, fsr_at="ground"),
        adc_bits=12,
        vref_v=3.3,
        rail_v=3.3,
    ),
    # The makers' linear circuit: an inverting op-amp with the FSR as input resistor, 1 V across it,
    # 47 kOhm feedback; the output is linear in the FSR's conductance and saturates at 5 V.
    "transimpedance": Estimator(
        front_end=Transimpedance(circuit="transimpedance", drive_v=1.0, feedback_kohm=47.0),
    ),
    # Another FSR: conductance growing as F^0.75 (a sub-linear log-log curve), a bare cell's 0.5 kOhm
    # series term, a lower actuation force and twice the part-to-part spread, read through a 5 V
    # divider with 22 kOhm.
    "power-law": Estimator(
        law_exponent=0.75,
        rs_kohm_n=25.0,
        ri_kohm=0.50,
        actuation_n=0.10,
        gain_sd=0.12,
        front_end=Divider(circuit="divider", supply_v=5.0, fixed_kohm=22.0),
    ),
    # A softer silicone cast with less preload: 0.30 N per FSR, 45 % of a load change arriving
    # through a 3 s lag.
    "soft-silicone": Estimator(
        preloads_n=(0.30, 0.30, 0.30),
        creep_fraction=0.45,
        creep_tau_s=3.0,
    ),
}


def rig(name: str) -> Estimator:
    """The nominal unit of the design `name`; ValueError naming the family if there is none."""
    try:
        return RIGS[name]
    except KeyError:
        raise ValueError(f"simulate.rig: no rig {name!r}; the family is {', '.join(RIGS)}") from None


def declared_front_end(est: Estimator) -> Circuit:
    """The circuit a lab with this estimator declares (batch.yaml `sensor.front_end`): its read-out,
    with the FSR's own series term under the silicone (R_i of the published calibration, docs/physics.md
    §6) as the series resistance it knows of."""
    return est.front_end.model_copy(update={"series_kohm": est.front_end.series_kohm + est.ri_kohm})
