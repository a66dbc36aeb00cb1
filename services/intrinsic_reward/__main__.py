from services.intrinsic_reward.service import main

main()
