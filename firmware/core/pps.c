#include "pps.h"

fw_pps_where fw_pps_locate(uint32_t t_prev, uint32_t t_edge, uint32_t t_pps)
{
    uint32_t into = t_pps - t_prev;
    if (into != 0u && into <= t_edge - t_prev)
        return FW_PPS_IN;
    return (int32_t)(t_pps - t_edge) > 0 ? FW_PPS_LATER : FW_PPS_STALE;
}

uint16_t fw_pps_latch(uint32_t t_prev, uint32_t t_edge, uint32_t t_pps)
{
    uint32_t period = t_edge - t_prev;
    if (period == 0u)
        return 0xFFFFu;
    uint64_t q = ((uint64_t)(t_pps - t_prev) << 16) / period;
    return q > 0xFFFFu ? (uint16_t)0xFFFFu : (uint16_t)q;
}
