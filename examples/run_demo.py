"""ermrl from Python: an experiment file, then an evolution and a test phase of your own.

Run from the repository root (about two minutes on 2 cores): python examples/run_demo.py
"""

import sys

import ermrl

file = sys.argv[1] if len(sys.argv) > 1 else "experiments/demo.yaml"
result = ermrl.Experiment.load(file, variant="quick").run()  # as `ermrl run FILE --variant quick`
print(result.summary[["task", "agent", "final_return_mean"]].to_string(index=False))

evolution = ermrl.evolve(
    "CartPole-v1", "sqlite:///runs/example.db", n_trials=4, n_seeds=1, training_steps=2000
)
print(f"best trial {evolution.best_trial} of {evolution.n_trials}: {evolution.best_params}")
test = ermrl.test(evolution.study_name, evolution.storage, training_steps=2000, seeds=[10, 11])
print(test.returns[["agent", "seed", "final_return"]].to_string(index=False))
