"""The comparative study: methods × loops × seeds on one system and one train/test split, on a local pool or Ray.

:mod:`~efficienttrack.study.jobs` (what a study and a job are, the presets), :mod:`~efficienttrack.study.methods`
(the methods by name and the jobs they give), :mod:`~efficienttrack.study.executors` (where jobs run),
:mod:`~efficienttrack.study.report` (table, ``study.json``, figure) and :mod:`~efficienttrack.study.run` (a whole study).
"""

from efficienttrack.study.jobs import STUDY_PRESETS, Job, Study, make_study
from efficienttrack.study.methods import METHODS, available_methods, make_jobs
from efficienttrack.study.report import Report, report
from efficienttrack.study.run import StudyResult, run_study

__all__ = [
    "METHODS",
    "STUDY_PRESETS",
    "Job",
    "Report",
    "Study",
    "StudyResult",
    "available_methods",
    "make_jobs",
    "make_study",
    "report",
    "run_study",
]
