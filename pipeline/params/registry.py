"""Every params section's model, in one place (for whole-file checks: presets, sweep cells).

Kept out of pipeline/params/__init__.py on purpose: a stage imports only its own section's
model, so its DVC code deps (its import closure) do not include the others', and editing one
stage's params model reruns only that stage.
"""

from __future__ import annotations

from pydantic import BaseModel

from pipeline.params import EnvParams, RunParams


def section_models() -> dict[str, type[BaseModel]]:
    """Every params section's model: "env", "" (the top-level lists) and each stage section."""
    from pipeline.params.critic_fidelity import CriticFidelityParams
    from pipeline.params.evaluate import EvaluateParams
    from pipeline.params.export import ExportParams
    from pipeline.params.extract import ExtractParams
    from pipeline.params.fit_critics import FitCriticsParams
    from pipeline.params.import_specialists import ImportSpecialistsParams
    from pipeline.params.interpolate import InterpolateParams
    from pipeline.params.mopderl import MopderlParams
    from pipeline.params.morld import MorldParams
    from pipeline.params.render import RenderParams
    from pipeline.params.report import ReportParams
    from pipeline.params.score import ScoreParams
    from pipeline.params.td3 import TD3Params
    from pipeline.params.train_pderl import TrainPderlParams
    from pipeline.params.train_specialist import TrainSpecialistParams

    return {
        "env": EnvParams,
        "": RunParams,
        "td3": TD3Params,
        "train_specialist": TrainSpecialistParams,
        "train_pderl": TrainPderlParams,
        "import_specialists": ImportSpecialistsParams,
        "fit_critics": FitCriticsParams,
        "critic_fidelity": CriticFidelityParams,
        "extract": ExtractParams,
        "mopderl": MopderlParams,
        "morld": MorldParams,
        "interpolate": InterpolateParams,
        "evaluate": EvaluateParams,
        "score": ScoreParams,
        "report": ReportParams,
        "export": ExportParams,
        "render": RenderParams,
    }
