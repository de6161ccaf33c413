/* The board-independent sampler: the sampling interrupt hands it each sample (and any PPS capture), it
 * numbers the sample, latches the PPS and queues the sample for the transmit path, which frames it.
 *
 * The counter counts sample periods, not frames sent: a sample that cannot be queued (ring full: the
 * transmit path fell behind) or that the board could not read still takes its counter value, so every loss
 * on the board shows on the host as a counter gap, which acquire/daq.py counts (counter_gaps, lost_frames;
 * `fieldlog info` prints them). Nothing is lost silently. */
#ifndef FW_DAQ_H
#define FW_DAQ_H

#include <stdbool.h>
#include <stdint.h>

#include "frame.h"
#include "ring.h"

/* What the board counts (each a uint32 that wraps). Written by the sampling interrupt except frames_sent. */
typedef struct {
    uint32_t samples;       /* sample periods (data-ready interrupts), = the next counter value */
    uint32_t frames_sent;   /* frames handed to the transmitter */
    uint32_t dropped;       /* samples not queued because the ring was full (each leaves a counter gap) */
    uint32_t overruns;      /* times the ring filled: runs of consecutive dropped samples */
    uint32_t bad_input;     /* samples the board could not read (ADC CRC error; bad emulated input record) */
    uint32_t pps_edges;     /* PPS edges latched to a sample period */
    uint32_t pps_stale;     /* PPS captures discarded: at or before the previous clock edge */
    uint32_t pps_double;    /* a second PPS capture before the first was framed (the first is kept) */
} fw_counters;

typedef struct {
    fw_ring ring;
    fw_counters c;
    uint32_t t_prev;        /* timer capture of the previous sample-clock edge */
    uint32_t t_pps;         /* pending PPS capture */
    bool have_prev;
    bool pps_pending;
    bool dropping;          /* the previous sample was dropped (overrun run in progress) */
} fw_daq;

void fw_daq_init(fw_daq *d);

/* The timer captured a PPS edge at t_pps (sampling-interrupt context). */
void fw_daq_pps(fw_daq *d, uint32_t t_pps);

/* Sample-clock edge at timer capture t_edge with the ADC's counts and, if temp_valid, the temperature in
 * centi-degrees C (sampling-interrupt context). */
void fw_daq_sample(fw_daq *d, const int32_t counts[FW_CHANNELS], uint32_t t_edge, bool temp_valid,
                   int16_t temp_cc);

/* A sample period whose data (and clock-edge capture) could not be read: the counter advances, bad_input
 * counts it, and the next period has no edge to latch a PPS against. */
void fw_daq_sample_bad(fw_daq *d);

/* Transmit path: the next frame into out; false when nothing is queued. */
bool fw_daq_next_frame(fw_daq *d, uint8_t out[FW_FRAME_SIZE]);

#endif
