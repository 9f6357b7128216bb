VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench lint clean mutate fuzz

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,cluster,field,service]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cutterpose demo

test: $(STAMP)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) benchmarks/bench.py

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

# the input readers' fuzz tests with 50x their CI examples, random (docs/results/robustness.md);
# a failure is printed with its input and kept in .hypothesis/ to replay
fuzz: $(STAMP)
	HYPOTHESIS_PROFILE=fuzz $(PY) -m pytest tests/test_fuzz_images.py tests/test_fuzz_files.py \
		tests/test_fuzz_poses.py -q

# mutation testing of the code that decides what the robot gets (docs/results/mutation.md):
# mutmut 3 ([tool.mutmut] in pyproject.toml: the files and the fast test selection); one
# worker by default (MUTATE_JOBS=2 on an idle 2-core machine halves the time). The survivors'
# table: mutants/survivors.md
MUTATE_JOBS ?= 1
MUTATE_TARGETS ?= \
	'cutterpose.budget.*' 'cutterpose.verdict.*' \
	'cutterpose.solvers.corners.x_edge_wear_effect__*' \
	'cutterpose.solvers.corners.x_edge_break_effect__*' \
	'cutterpose.solvers.corners.x__corner_fit__*' \
	'cutterpose.solvers.corners.x__least_squares_step__*' \
	'cutterpose.solvers.corners.x_fit_offset__*' 'cutterpose.solvers.corners.x__noise_cov__*' \
	'cutterpose.solvers.corners.x__pose_cov__*' 'cutterpose.solvers.corners.x_pose_std__*' \
	'cutterpose.solvers.corners.x_corner_budget__*' \
	'cutterpose.solvers.radius_budget.x_edge_variation_mm__*' \
	'cutterpose.solvers.radius_budget.x_radius_profile_cov__*' \
	'cutterpose.solvers.radius_budget.x_budget_from_fit__*' \
	'cutterpose.solvers.edge_band.x_variance_components__*' \
	'cutterpose.solvers.edge_band.x_edge_noise_cov__*' \
	'cutterpose.solvers.edge_band.x__look_spread__*' \
	'cutterpose.solvers.edge_band.x__calibration_parts__*' \
	'cutterpose.solvers.edge_band.x_band_budget__*' 'cutterpose.solvers.edge_band.x_band_verdict__*' \
	'cutterpose.geometry.pose.*' \
	'cutterpose.geometry.camera.xǁCameraǁ*' 'cutterpose.geometry.camera.xǁDivisionCameraǁ*' \
	'cutterpose.geometry.camera.xǁPinholeCameraǁ*' \
	'cutterpose.robot.frames.*' 'cutterpose.robot.grasp.*' 'cutterpose.robot.locate.*' \
	'cutterpose.calibration.handeye.x__to_own__*' 'cutterpose.calibration.handeye.x__verdict__*' \
	'cutterpose.calibration.handeye.x_load_handeye__*' \
	'cutterpose.calibration.handeye.xǁHandEyeResultǁ*' \
	'cutterpose.experiments.report.x_trial_rows__*' 'cutterpose.experiments.report.x_summarize__*' \
	'cutterpose.experiments.report.x__std__*' 'cutterpose.experiments.report.x__mean__*' \
	'cutterpose.experiments.report.x__pct__*'

mutate: $(STAMP)
	$(VENV)/bin/mutmut run --max-children $(MUTATE_JOBS) $(MUTATE_TARGETS)
	$(PY) benchmarks/mutation_report.py $(MUTATE_TARGETS) > mutants/survivors.md
	@echo "survivors: mutants/survivors.md"

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
