"""The paper's experiments on sgf-pipeline runs: Tables 1-4, the robustness suite and the leave-one-out.

``sgf-report DIR`` turns a run or a sweep into the tables; ``conf/`` holds the experiments
(``+experiment=...``), the extensions turned off one at a time (``+ablate=...``) and the
perturbed robots and worlds (``+perturbation=...``).
"""

from pathlib import Path

#: The experiments' config groups (on sgf-run's search path through the ``sgf_pipeline.conf`` entry point).
CONF = Path(__file__).resolve().parent / "conf"
