# The two commands of the README: `make demo` runs the main job, `make test` runs the tests.
# Both set everything up first (Debian packages, .venv/, the project); a second run skips set-up.
VENV := .venv
export MUJOCO_GL ?= egl
export RAY_AUTH_MODE ?= disabled
# the pose strategies `sygrid models choose-pose` measures (the unrefined and RGB-only ones never reach the bar;
# hybrid+icp never beat depth+icp)
POSE_CANDIDATES := rgbd+icp,depth+icp,depth+search,hybrid+search

.PHONY: setup lock demo test lint bench models models-sim-cell transfer transfer-ablation

setup:
	@bash scripts/setup.sh

# Re-resolve the pinned versions (constraints.txt) from pyproject.toml in a scratch venv; review the diff, then
# `make test` (set-up reinstalls .venv from the new pins).
lock:
	bash scripts/lock.sh

demo: setup
	$(VENV)/bin/sygrid demo

test: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/python -m pytest -q

bench: setup
	$(VENV)/bin/sygrid bench physics

# Retrain the shipped models (models/builtin) from scratch: the datasets, both networks, the model cards.
# Hours on a 2-core CPU; every step resumes where it stopped when run again.
MIXED_EPOCHS := 8
models: setup
	$(VENV)/bin/sygrid generate launch/recipes/builtin_train.json --out datasets/builtin_train --count 2000 --seed 0 --workers 2
	$(VENV)/bin/sygrid generate launch/recipes/builtin_test.json --out datasets/builtin_test --count 200 --seed 1000 --workers 2
	$(VENV)/bin/sygrid generate launch/recipes/builtin_train_transfer.json --out datasets/builtin_train_transfer --count 2000 --seed 0 --workers 2
	# the detector (models/builtin/detector.card.md): TrainConfig's defaults on the plain items, then fine-tuned on the
	# plain and the randomised items together (the transfer recipe, docs/bench/transfer.md)
	$(VENV)/bin/sygrid train detector --data datasets/builtin_train --out runs/detector_plain --threads 2 --seed 0 --half-weights $(if $(wildcard runs/detector_plain/last.pt),--resume)
	$(VENV)/bin/sygrid train detector --data datasets/builtin_train --data datasets/builtin_train_transfer --init runs/detector_plain/best.pt --epochs $(MIXED_EPOCHS) --lr 0.002 --out runs/detector --threads 2 --seed 0 --half-weights $(if $(wildcard runs/detector/last.pt),--resume)
	# the shipped pose model: 12 epochs, then resumed to 24 (see models/builtin/pose.card.md)
	test -f runs/pose/last.pt || $(VENV)/bin/sygrid train pose --data datasets/builtin_train --out runs/pose --epochs 12 --threads 1 --seed 0
	$(VENV)/bin/sygrid train pose --data datasets/builtin_train --out runs/pose --epochs 24 --threads 1 --seed 0 --resume
	# the detector looks at the bin's box upscaled 1.25 times, at confidence 0.2 (docs/bench/detection.md and
	# perception.md); the pose strategies and the verification threshold are chosen on calibration views (the test
	# recipe with another seed, noise-free and through the OAK-D model), then the folder is packed again so that its
	# cards measure them
	$(VENV)/bin/sygrid models pack --detector runs/detector --pose runs/pose --out models/builtin --test-data datasets/builtin_test --scale 1.25 --conf-threshold 0.2
	$(VENV)/bin/sygrid generate launch/recipes/builtin_test.json --out datasets/builtin_cal --count 80 --seed 5000 --workers 2
	$(VENV)/bin/sygrid generate launch/recipes/builtin_test_noisy.json --out datasets/builtin_cal_noisy --count 80 --seed 5000 --workers 2
	$(VENV)/bin/sygrid models choose-pose --models models/builtin --data datasets/builtin_cal --data datasets/builtin_cal_noisy --strategies $(POSE_CANDIDATES) --threads 1
	$(VENV)/bin/sygrid models pack --detector runs/detector --pose models/builtin --out models/builtin --test-data datasets/builtin_test --scale 1.25 --conf-threshold 0.2

# The simulated cell's models (models/sim_cell): the shipped detector and pose network (models/builtin's), with the
# pose strategies and the verification threshold chosen on views of the cell's camera (0.82-0.98 m above the bin),
# noise-free and through the OAK-D model, other views than the test set's; packed again so that the cards measure
# them. About half an hour on a 2-core CPU.
models-sim-cell: setup
	$(VENV)/bin/sygrid generate launch/recipes/sim_cell_test.json --out datasets/sim_cell_test --count 100 --seed 1000 --workers 2
	$(VENV)/bin/sygrid models pack --detector models/builtin --pose models/builtin --out models/sim_cell --test-data datasets/sim_cell_test
	$(VENV)/bin/sygrid generate launch/recipes/sim_cell_test.json --out datasets/sim_cell_val --count 40 --seed 2000 --workers 2
	$(VENV)/bin/sygrid generate launch/recipes/sim_cell_test_noisy.json --out datasets/sim_cell_val_noisy --count 40 --seed 2000 --workers 2
	$(VENV)/bin/sygrid models choose-pose --models models/sim_cell --data datasets/sim_cell_val --data datasets/sim_cell_val_noisy --strategies $(POSE_CANDIDATES) --threads 1
	$(VENV)/bin/sygrid models pack --detector models/builtin --pose models/sim_cell --out models/sim_cell --test-data datasets/sim_cell_test

# The transfer matrix (docs/bench/transfer.md): the shipped detector on the test sources of the transfer issue,
# the same-recipe test set, the rasteriser's, the randomised recipe's and the held-apart families'.
TRANSFER_SOURCES := builtin_test builtin_test_raster builtin_test_random builtin_test_heldout
transfer: setup
	for s in $(TRANSFER_SOURCES); do $(VENV)/bin/sygrid generate launch/recipes/$$s.json --out datasets/$$s --count 200 --seed 1000 --workers 2 || exit 1; done
	$(VENV)/bin/sygrid bench transfer --detector builtin=models/builtin --source builtin=datasets/builtin_test \
		--source raster=datasets/builtin_test_raster --source random=datasets/builtin_test_random \
		--source heldout=datasets/builtin_test_heldout --held-apart heldout --cards

# The transfer ablation (docs/bench/transfer.md): the randomised training recipe with every knob on, with each knob
# off in turn (launch/recipes/ablation/), and with none (the plain recipe); a short run of the shipped training
# recipe at width p (a knob changes the data, not the network: the cheaper width ranks them) on each (and on the
# randomised items without the photometric augmentation, and with a second seed: the runs' own spread), every
# detector on the plain, randomised and held-apart test sources. Hours on a 2-core CPU; every step resumes where it
# stopped. ABLATION_ITEMS / ABLATION_EPOCHS size the runs.
ABLATION_KNOBS := surfaces parts lighting distractors camera geometry
ABLATION_ITEMS ?= 300
ABLATION_EPOCHS ?= 20
ABLATION_RUNS := random plain $(addprefix without_,$(ABLATION_KNOBS)) random_seed1 random_no_photometric
PHOTOMETRIC_OFF := {"hsv_h": 0, "hsv_s": 0, "hsv_v": 0, "brightness": 0, "contrast": 0, "blur_p": 0, "noise_p": 0}
transfer-ablation: setup
	for s in builtin_test builtin_test_random builtin_test_heldout; do $(VENV)/bin/sygrid generate launch/recipes/$$s.json --out datasets/$$s --count 200 --seed 1000 --workers 2 --no-progress || exit 1; done
	$(VENV)/bin/sygrid generate launch/recipes/builtin_train_random.json --out datasets/ablation/random --count $(ABLATION_ITEMS) --seed 0 --workers 2 --no-progress
	$(VENV)/bin/sygrid generate launch/recipes/builtin_train.json --out datasets/ablation/plain --count $(ABLATION_ITEMS) --seed 0 --workers 2 --no-progress
	for k in $(ABLATION_KNOBS); do $(VENV)/bin/sygrid generate launch/recipes/ablation/without_$$k.json --out datasets/ablation/without_$$k --count $(ABLATION_ITEMS) --seed 0 --workers 2 --no-progress || exit 1; done
	for v in $(ABLATION_RUNS); do \
		case $$v in random_seed1) data=random seed=1 aug='{}';; random_no_photometric) data=random seed=0 aug='$(PHOTOMETRIC_OFF)';; *) data=$$v seed=0 aug='{}';; esac; \
		$(VENV)/bin/sygrid train detector --data datasets/ablation/$$data --out runs/ablation/$$v --epochs $(ABLATION_EPOCHS) --width p --seed $$seed --augment "$$aug" --threads 2 --no-progress $$(test -f runs/ablation/$$v/last.pt && echo --resume) || exit 1; \
	done
	$(VENV)/bin/sygrid bench transfer --name transfer_ablation $(foreach v,$(ABLATION_RUNS),--detector $(v)=runs/ablation/$(v) --home $(v)=$(if $(filter plain,$(v)),builtin,random)) \
		--source builtin=datasets/builtin_test --source random=datasets/builtin_test_random \
		--source heldout=datasets/builtin_test_heldout --held-apart heldout
