"""How far a bf16 training gradient is from the float32 one, parameter by parameter, on a trained model.

Loads a model snapshot (e.g. one of ``bench/precision_study.py``'s runs), plays the same B training
episodes with the same action noise once in float32, once with ``precision: bf16`` and once more in
float32 (a determinism check: the two float32 gradients must be equal), and prints, per parameter,
the float32 gradient's norm, the bf16 gradient's relative error ``|g_bf16 - g_fp32| / |g_fp32|``, the
cosine between them and, for scale, the same relative difference between the float32 gradients of
this batch and of another B episodes (the sampling noise every update carries anyway). ``tests/test_train_equivalence.py`` checks the same on a fresh tiny model;
this asks whether a trained one, where bf16 runs of the learning check stop calling ``Done``, is
any different (docs/training.md, Precision).

    python bench/precision_gradients.py SNAPSHOT [--batch 32] [--seed 11]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from mapless.agent.acting import observation_keys
from mapless.checkpoint import load_model
from mapless.config import from_dict
from mapless.train.builders import BuiltinLibrary, training_env, training_sampler
from mapless.train.config import TrainConfig
from mapless.train.rollout import accumulate_gradients, make_actor, run_batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("snapshot", help="model snapshot, resumable checkpoint or run folder")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seed", type=int, default=11, help="seed of the episodes and their action noise")
    args = parser.parse_args()
    torch.set_num_threads(1)

    model, config_data, counters = load_model(args.snapshot)
    config = from_dict(TrainConfig, config_data)
    model.train()
    scenes = config.env.scene_list()
    library = BuiltinLibrary(config)()  # the run's own scenes and simulator settings
    library.prepare(scenes, progress=False)
    rng = np.random.default_rng(args.seed)
    sampler = training_sampler(config, library, seed=args.seed)
    batches = []
    for _ in range(2):
        episodes = [sampler.sample(rng) for _ in range(args.batch)]
        batches.append((episodes, rng.random((args.batch, config.env.max_steps))))
    env = training_env(config, library, args.batch)

    played = []
    passes = [("fp32", batches[0]), ("bf16", batches[0]), ("fp32", batches[0]), ("fp32", batches[1])]
    for precision, (episodes, noise) in passes:
        torch.manual_seed(0)  # the same dropout masks in every pass
        actor = make_actor(model, precision=precision)
        model.zero_grad(set_to_none=True)
        trajectory = run_batch(actor, env, episodes, noise, observation_keys(model), torch.device("cpu"))
        accumulate_gradients(actor, trajectory, config.loss)
        grads = {n: p.grad.double() for n, p in model.named_parameters() if p.grad is not None}
        played.append((trajectory.actions.clone(), grads))
    (fp32_actions, fp32), (bf16_actions, bf16), (again_actions, again), (_, other) = played

    print(f"{args.snapshot}: {counters.get('episodes', '?')} training episodes, B = {args.batch}")
    print(f"same actions in bf16: {torch.equal(fp32_actions, bf16_actions)}; "
          f"float32 twice: same actions {torch.equal(fp32_actions, again_actions)}, "
          f"same gradient {all(torch.equal(fp32[n], again[n]) for n in fp32)}")  # fmt: skip
    print(
        f"{'parameter':44s} {'|g fp32|':>10s} {'bf16 rel. error':>15s} {'cosine':>8s} {'another batch':>13s}"
    )
    for name, exact in fp32.items():
        norm = exact.norm().item()
        if norm == 0:
            continue
        error = (bf16[name] - exact).norm().item() / norm
        cosine = torch.nn.functional.cosine_similarity(bf16[name].flatten(), exact.flatten(), dim=0).item()
        sampling = (other[name] - exact).norm().item() / norm
        print(f"{name:44s} {norm:10.3e} {error:15.4f} {cosine:8.4f} {sampling:13.2f}")


if __name__ == "__main__":
    main()
