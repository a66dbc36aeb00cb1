from services.dynamics_learner.service import main

main()
