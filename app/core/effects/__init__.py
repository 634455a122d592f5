"""The physical effects a model may add to the paper's baseline (ids from the
CLI contract). Each relaxes one baseline assumption and lives in its own module:

    hyperelastic      app.core.effects.hyperelastic   (large deformation, neo-Hookean)
    viscoelastic      app.core.effects.viscoelastic   (Prony series, hereditary integral)
    sliding-bottom    app.core.effects.boundary       (bottom face slides on the table)
    probe-slip        app.core.effects.boundary       (probe face slides on the surface)
    compressibility   app.core.effects.compressibility (Poisson's ratio free)
    inclusion         app.core.effects.inclusion      (an undescribed region, located from the misfit)

Each module states its parameters, how it changes the forward model (see
:class:`app.core.effects.model.EffectProblem`) and the signature it leaves in
the misfit (its ``evidence`` function, used by the diagnosis).
"""

from __future__ import annotations

from dataclasses import dataclass

EFFECT_IDS = ("hyperelastic", "viscoelastic", "sliding-bottom", "probe-slip", "compressibility", "inclusion")

_AVAILABLE: tuple[str, ...] = EFFECT_IDS


def available() -> tuple[str, ...]:
    """Effect ids implemented in this version."""
    return _AVAILABLE


@dataclass(frozen=True)
class Parameter:
    """A free parameter an effect adds. ``scale``: 'log' (positive, searched in
    log) or 'logit' (bounded, searched in logit of the bounds)."""

    name: str
    default: float
    lower: float
    upper: float
    scale: str = "log"
    description: str = ""


@dataclass(frozen=True)
class EffectInfo:
    """What an effect is, for people and for the diagnosis.

    ``channel``: where its signature shows first, 'force' (the force log) or
    'images' (the displacement field seen in the frames). ``n_parameters`` is what
    the information criterion charges for adding it (a switch with no continuous
    parameter is charged as one)."""

    id: str
    title: str
    assumption: str  # the baseline assumption it relaxes
    channel: str
    parameters: tuple[Parameter, ...] = ()
    n_parameters: int = 1


VISCO_PARAMETERS = (
    Parameter("g1", 0.3, 0.0, 0.95, "logit", "relaxing fraction of the instantaneous modulus"),
    Parameter("tau1_s", 3.0, 0.05, 1000.0, "log", "relaxation time, s"),
)
NU_PARAMETER = Parameter("nu", 0.45, 0.3, 0.4995, "logit", "Poisson's ratio")

INFO = {
    "hyperelastic": EffectInfo("hyperelastic", "large deformation (neo-Hookean)",
                               "small strains: force proportional to probe travel", "force", (), 1),
    "viscoelastic": EffectInfo("viscoelastic", "time-dependent relaxation (Prony series)",
                               "no time dependence", "force", VISCO_PARAMETERS, 2),
    "sliding-bottom": EffectInfo("sliding-bottom", "specimen slides on the table",
                                 "bottom face bonded to the table", "images", (), 1),
    "probe-slip": EffectInfo("probe-slip", "probe slides on the surface",
                             "probe face bonded to the surface", "images", (), 1),
    "compressibility": EffectInfo("compressibility", "compressible tissue (free Poisson's ratio)",
                                  "Poisson's ratio fixed at 0.49", "images", (NU_PARAMETER,), 1),
    "inclusion": EffectInfo("inclusion", "an undescribed inclusion",
                            "the regions in experiment.toml are all there is", "images", (), 4),
}


def parameters_of(effects) -> tuple[Parameter, ...]:
    """The extra parameters of a set of effects (moduli excluded), in a fixed order."""
    out = []
    for e in EFFECT_IDS:
        if e in effects:
            out.extend(INFO[e].parameters)
    return tuple(out)


def check(effects) -> tuple[str, ...]:
    """Validate and order effect ids (contract order)."""
    from app.core.errors import ElastoidError

    effects = tuple(effects)
    for e in effects:
        if e not in EFFECT_IDS:
            raise ElastoidError(f"unknown effect {e!r}; the ids are {', '.join(EFFECT_IDS)}")
    return tuple(e for e in EFFECT_IDS if e in effects)


def misfit_change(before_px: float, after_px: float) -> str:
    """"falls from 0.89 to 0.83 px", "rises from 0.89 to 1.59 px" or "stays at 0.89 px"."""
    b, a = f"{before_px:.2f}", f"{after_px:.2f}"
    if a == b:
        return f"stays at {b} px"
    return f"{'falls' if after_px < before_px else 'rises'} from {b} to {a} px"
