/*
 * main_footprint.c - the smallest image that links everything the PX4 module
 * runs: the traffic table, the heading state and one covey_command on a static
 * scratch. arm-none-eabi-size of this ELF is the flash and RAM the policy costs
 * an autopilot (weights, code, libm, table, scratch).
 */
#include "covey_traffic.h"
#include "semihost.h"

static covey_scratch_t scratch;
static covey_traffic_t traffic;
static covey_heading_t heading;

int main(void)
{
    const covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    const covey_goal_t goal = {10.0f, 0.0f};
    const covey_vehicle_t other = {5.0f, 1.0f, 3.0f, 0u};
    covey_traffic_init(&traffic);
    covey_traffic_put(&traffic, 1u, &other);
    covey_traffic_prune(&traffic, 0u, cfg.max_neighbour_age_us);
    const covey_vehicle_t own = {0.0f, 0.0f, covey_heading_for_goal(&heading, 0.0f, 0.0f, &goal), 0u};
    covey_command_t out;
    covey_status_t st = covey_command(&cfg, &own, &goal, traffic.report, traffic.n, 0u, &scratch, &out);
    covey_heading_after_command(&heading, &out);
    return (int)st;
}
