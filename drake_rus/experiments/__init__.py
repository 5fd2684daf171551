"""The seed paper's section III studies on the virtual cohort (``drake-rus study``).

Studies (each a list of independent runs; a run is a
:class:`~drake_rus.experiments.specs.StudyTask`, its result a JSON file):

- ``er-sweep`` (III-C, Fig. 7d): exploration ratios 0..100% in 10% steps per patient; ER 0
  is the initial alignment alone, in both modes.
- ``starts`` (III-D, Fig. 9d): at the critical ER, five random starts per patient inside the
  E-ROI, drawn where the kidney is visible (the paper's II-A assumption (i)).
- ``efficiency`` (III-E, Fig. 10): OP (at T* of the registered pose), GT-OP, NOP and SL per
  patient, and beyond the paper OP-PE (OP's pose with the predicted_end pivot): V against n
  and eps pole to pole (the paper's), the whole pivot's beside them, n and eps to reach
  V = 0.9, the tilt cap, and the kidney volume reconstructed from each sweep's masks.
- ``closed-loop``: a few closed-loop dynamic scans beside their kinematic twins (the paper
  study's check).
- ``template`` (beyond the paper, issue 18): localization at one ER with template variants
  that differ from the patient by known amounts, each run recording the template's
  distance from the patient's kidney. A patient may be a real body (a patient path);
  ``StudyOptions.posture`` (or a ``@decubitus`` suffix) lays patients in a posture.

Patients are generated (``test:K``...), real CT kidneys in generated bodies (``ct:``, also
as cohorts ``ct:DIR:0-14`` / ``ct:DIR:firstN``) or real bodies, each kind grouped apart; the
registration template is the generated one or another (``StudyOptions.template``: ``real``,
built from CT kidneys without the patients' cases), recorded in every run.

Every run is kinematic (the fast twin, default) or, with ``mode`` "closed-loop", a full
closed-loop scan on the Drake diagram with the same run record. Modules, lowest first:

- :mod:`.kinematic`: the kinematic twin (exploration, pivots, strategies, no dynamics);
- :mod:`.analysis`: the statistics (paired t-tests, critical ER, Bonferroni, equivalence);
- :mod:`.specs`: what a study asks for: patient specs, options, the typed run
  (``StudyTask``) and the generators of a study's runs;
- :mod:`.keys`: a run's id, settings key, resolved inputs and provenance;
- :mod:`.templates`: the template study's template variants and distances, and what a
  study's template is (``template_info``);
- :mod:`.ct_cohort`: ``ct:DIR:SELECTION`` cohorts expanded, and the patients whose case
  built the template;
- :mod:`.patients`: a run's prepared patient, ER travel and random starts;
- :mod:`.kinematic_runs` and :mod:`.closed_loop_runs`: one run in each mode;
- :mod:`.tasks`: ``run_task``, one run dispatched to its mode (what the batch runner calls);
- :mod:`.results`: finished runs loaded, matched to their tasks, and their shared settings;
- :mod:`.report`: tables, figures and ``report.md``; :mod:`.cli`: the ``study`` command.
"""
