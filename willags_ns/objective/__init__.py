"""What training minimises: the masked reconstruction loss and the regularisers that join it."""
