/* Polled USART transmit (RM0090 §30). 8N1, oversampling by 16. */
#ifndef FW_USART_H
#define FW_USART_H

#include <stddef.h>
#include <stdint.h>

/* Enable the USART at `base`, on a bus of pclk_hz, as a transmitter at `baud`. */
void usart_init(uint32_t base, uint32_t pclk_hz, uint32_t baud);

/* Write len bytes, waiting for TXE before each (interrupts keep running meanwhile). */
void usart_write(uint32_t base, const uint8_t *data, size_t len);

#endif
