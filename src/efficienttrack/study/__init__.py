"""The comparative study: methods × loops × seeds on one system and one train/test split, on a local pool or Ray.

:mod:`~efficienttrack.study.jobs` (what a study and a job are, the presets, the validation split),
:mod:`~efficienttrack.study.methods` (the methods by name and the jobs they give, a baseline's run with the
validation references),
:mod:`~efficienttrack.study.executors` (where jobs run),
:mod:`~efficienttrack.study.report` (table, ``study.json``, figure) and :mod:`~efficienttrack.study.run` (a whole study);
:mod:`~efficienttrack.study.ablations` (variants of one EfficientTrack setting at equal data) and
:mod:`~efficienttrack.study.ablation_report` (their tables, ``ablation.json``, figure).
"""

from efficienttrack.study.ablation_report import AblationReport, ablation_report
from efficienttrack.study.ablations import ABLATIONS, Ablation, ablation_jobs, get_ablation, make_ablation_study
from efficienttrack.study.jobs import STUDY_PRESETS, Job, Study, Variant, make_study
from efficienttrack.study.methods import METHODS, available_methods, make_jobs
from efficienttrack.study.report import Report, report
from efficienttrack.study.run import StudyResult, run_ablation, run_study

__all__ = [
    "ABLATIONS",
    "METHODS",
    "STUDY_PRESETS",
    "Ablation",
    "AblationReport",
    "Job",
    "Report",
    "Study",
    "StudyResult",
    "Variant",
    "ablation_jobs",
    "ablation_report",
    "available_methods",
    "get_ablation",
    "make_ablation_study",
    "make_jobs",
    "make_study",
    "report",
    "run_ablation",
    "run_study",
]
