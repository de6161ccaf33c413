/* Polled USART transmit and interrupt-driven receive enable (RM0090 §30). 8N1, oversampling by 16. */
#ifndef FW_USART_H
#define FW_USART_H

#include <stddef.h>
#include <stdint.h>

/* Enable the USART at `base` on a bus of pclk_hz at `baud`; rx_irq: also the receiver with its RXNE
 * interrupt (the caller enables the IRQ in the NVIC). */
void usart_init(uint32_t base, uint32_t pclk_hz, uint32_t baud, int rx_irq);

/* Write len bytes, waiting for TXE before each (interrupts keep running meanwhile). */
void usart_write(uint32_t base, const uint8_t *data, size_t len);

#endif
