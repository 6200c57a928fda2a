/*
 * main_footprint.c - the smallest image that links the whole policy core:
 * one covey_command on a static scratch. arm-none-eabi-size of this ELF is the
 * flash and RAM the policy costs an autopilot (weights, code, libm, scratch).
 */
#include "covey_policy.h"
#include "semihost.h"

static covey_scratch_t scratch;
static covey_vehicle_t nbrs[COVEY_MAX_INPUTS];

int main(void)
{
    const covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    const covey_vehicle_t own = {0.0f, 0.0f, 0.0f, 0u};
    const covey_goal_t goal = {10.0f, 0.0f};
    covey_command_t out;
    covey_status_t st = covey_command(&cfg, &own, &goal, nbrs, 1, 0u, &scratch, &out);
    return (int)st;
}
