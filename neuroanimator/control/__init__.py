"""Control synthesis through neural-network emulators (thesis chapter 5, sections 6.2-6.3, App. G).

A *job* asks for a controller: a task (``catalog.tasks.TASKS``) or a model with a goal, an objective,
and the optimiser's settings (``goals.spec``). ``validation.validate_job`` turns a request
(``contracts.controller.JobCreate``, or its JSON) into a ``JobSpec`` without importing PyTorch or
MuJoCo (an API process calls it on submission); ``job.run_job`` validates again (against the worker's
artifacts), optimises the controller by backpropagation through time in the artifact's torch
emulator, with momentum, replays it on MuJoCo and, if it misses there, refines it on an emulator
corrected along the replay.

    JobCreate (the API body) --validate_job--> JobSpec (queued, run) --run_job--> JobOutcome
    (stored with the job's id as ``contracts.controller.JobResult``)

Modules: ``validation`` (``validate_job``; no torch), ``splines`` (Catmull-Rom controls in torch),
``objectives`` (J in torch), ``bptt`` (the emulator objective and its gradient), ``synthesis`` (the
momentum optimiser), ``search`` and ``gauss_newton`` (global search, refinement), ``replay`` (MuJoCo
replay), ``gradient_free`` (Nelder-Mead and CMA-ES baselines), ``job`` (``run_job``). What a job asks
for (spec, terms, criteria) is ``goals``, below this package, so the torch-free API reads it.
"""
