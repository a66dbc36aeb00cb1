from services.policy_learner.service import main

main()
