/* Lock-free single-producer single-consumer ring of samples: the sampling interrupt pushes, the transmit
 * path (main loop) pops. head is written only by the producer, tail only by the consumer; both run freely
 * modulo 2^32 and head - tail is the fill. C11 atomics with release/acquire order make a slot's contents
 * visible before the index that publishes it (on a single Cortex-M core these are plain loads and stores
 * with compiler barriers; on the host they are real fences). A full ring refuses the push: the newest
 * sample is the one dropped, and the caller counts it. */
#ifndef FW_RING_H
#define FW_RING_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>

#include "frame.h"

#ifndef FW_RING_CAPACITY
#define FW_RING_CAPACITY 64u  /* samples: 128 ms at 500 Hz; a power of two */
#endif
_Static_assert((FW_RING_CAPACITY & (FW_RING_CAPACITY - 1u)) == 0, "FW_RING_CAPACITY: a power of two");

typedef struct {
    _Atomic uint32_t head;  /* next slot to write; producer only */
    _Atomic uint32_t tail;  /* next slot to read; consumer only */
    fw_sample slot[FW_RING_CAPACITY];
} fw_ring;

void fw_ring_init(fw_ring *r);
bool fw_ring_push(fw_ring *r, const fw_sample *s);  /* false (nothing written) when full */
bool fw_ring_pop(fw_ring *r, fw_sample *out);       /* false when empty */
uint32_t fw_ring_fill(fw_ring *r);

#endif
