# Shortcuts over the project's scripts (each does its own set-up).
.PHONY: run test image compose-e2e compose-up compose-down

run:            ## the main job: a local LCRL run on the linear example
	bash scripts/run.sh

test:           ## the whole test suite (what CI runs)
	bash scripts/test.sh

image:          ## the lcrl:local container image, built from nothing pulled
	bash deploy/build-image.sh

compose-e2e:    ## build the image, run the compose stack, kill an actor, check
	bash deploy/compose-e2e.sh

compose-up: image  ## graph builder + learner + 2 actors in containers
	docker-compose -f deploy/compose.yaml up --scale actor=2

compose-down:
	docker-compose -f deploy/compose.yaml down
