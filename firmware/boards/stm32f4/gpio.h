/* GPIO pin configuration (RM0090 §8). */
#ifndef FW_GPIO_H
#define FW_GPIO_H

#include <stdint.h>

enum { GPIO_IN = 0, GPIO_OUT = 1, GPIO_AF = 2, GPIO_ANALOG = 3 };

/* Pin `pin` of the port at `port` (GPIOA_BASE...) in `mode`; with GPIO_AF, alternate function `af`. Very
 * high output speed; no pull. */
void gpio_config(uint32_t port, unsigned pin, unsigned mode, unsigned af);

void gpio_write(uint32_t port, unsigned pin, int high);

#endif
